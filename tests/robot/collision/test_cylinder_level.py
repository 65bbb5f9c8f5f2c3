"""Level 3 of the broad phase against a cylinder: a robot polytope's hull vertices.

A robot polytope (a mesh, a convex piece, a box) against a world cylinder (the
bottle, and the bottle shrunk by the contact tolerance for the gripper) is free
when all its hull vertices lie more than ``BROAD_MARGIN`` beyond a cap's plane or
the side plane across the direction from the axis to their centroid, and
collides when one of them lies deeper than ``INSIDE_DEPTH`` inside (a hull
vertex is a vertex of the geometry's triangles). Checked here, for the Panda,
the UR5 with the Robotiq 2F-85 and two user URDFs (a concave mesh forearm;
``write_mixed_arm``: that forearm, boxes and a convex mesh) in the bottle's world,
on configurations near contact (IK solutions around the bottle and, pair by pair,
both sides of its contact bisected to 1e-4 rad):

* every (pair, configuration) the compiled kernel or the NumPy level decides,
  coal (as the checker asks it) decides the same, and both sides are decided
  often;
* the kernel decides only what the NumPy level decides the same, and
  everything the NumPy level decides with its limits 2e-9 m stricter (the
  kernel's slack is 1e-9 m): a comparison by tolerance, valid on any CPU;
* the checker's decisions with the level equal those of a checker without it.
"""

from __future__ import annotations

import numpy as np
import pytest
from helpers import pair_contact
from urdfs import assert_same_without_level, bottle_checker, level_columns

from gcm_pipeline.robot import kernels
from gcm_pipeline.robot.collision import broadphase
from gcm_pipeline.robot.collision.broadphase import BROAD_MARGIN, INSIDE_DEPTH, stacked
from gcm_pipeline.robot.ik import solve_ik

#: Each test starts with the kernels on, whatever the environment says.
pytestmark = pytest.mark.usefixtures("kernels_on")

_ROBOTS = ("panda", "ur5_robotiq", "user_arm", "user_mixed")


def _checker(name, tmp_path_factory):
    return bottle_checker(name, tmp_path_factory.mktemp("arm"))


def _around_the_bottle(robot, n, seed):
    """IK solutions with the grasp frame within 25 cm of the bottle's axis, any heading."""
    rng = np.random.default_rng(seed)
    a = rng.uniform(0.0, 2.0 * np.pi, n)
    t = np.tile(np.eye(4), (n, 1, 1))
    z = -np.stack([np.cos(a), np.sin(a), rng.uniform(-0.5, 0.5, n)], axis=1)
    z /= np.linalg.norm(z, axis=1, keepdims=True)
    y = np.cross(z, rng.normal(size=(n, 3)))
    y /= np.linalg.norm(y, axis=1, keepdims=True)
    t[:, :3, 0], t[:, :3, 1], t[:, :3, 2] = np.cross(y, z), y, z
    reach = rng.uniform(0.0, 0.25, n)[:, None]
    t[:, :3, 3] = [0.5, 0.0, 0.0] + np.column_stack([np.zeros((n, 2)), rng.uniform(0, 0.3, n)])
    t[:, :3, 3] -= reach * z
    res = solve_ik(robot, t)
    return res.q[res.success]


def _columns(checker):
    """The cylinder columns: [(screen, column, pair)]."""
    return level_columns(checker, "cylinders")


@pytest.fixture(scope="module", params=_ROBOTS)
def case(request, tmp_path_factory):
    """A checker, and per cylinder column configurations near that pair's contact."""
    checker = _checker(request.param, tmp_path_factory)
    robot = checker.robot
    q = np.concatenate([robot.random_configurations(400, 7), _around_the_bottle(robot, 600, 8)])
    near = {c: np.concatenate([q, pair_contact(checker, q, c)]) for _, _, c in _columns(checker)}
    plain = _checker(request.param, tmp_path_factory)  # the same without the level
    for screen in plain._screens.values():
        screen.cylinders.clear()
    return request.param, checker, near, plain


def _numpy_level(checker, screen, k, q):
    """The NumPy level's status of column ``k`` on every row of ``q`` (kernels' codes)."""
    frames = checker._frames.compute(q)
    rows, inside = broadphase._world_cylinder_level(
        (frames.rots, frames.poss), np.arange(len(q)), screen.cylinders[k]
    )
    status = np.full(len(q), kernels.FREE, dtype=np.int8)
    status[rows] = np.where(inside, kernels.COLLIDES, kernels.UNDECIDED)
    return status


def _kernel_level(compiled, checker, screen, k, q):
    frames = checker._frames.compute(q)
    joint, *limits = checker._compiled_screen(screen)[3][k]
    return compiled.hull_vs_cylinder(stacked(frames.transforms)[joint], np.arange(len(q)), *limits)


def test_cylinder_level_decides_as_coal(compiled, case):
    """Every row either level decides, coal decides the same; it decides both ways."""
    name, checker, near, _ = case
    columns = _columns(checker)
    assert columns, name  # arm links and gripper pieces against the bottle
    decided = {kernels.FREE: 0, kernels.COLLIDES: 0}
    for screen, k, c in columns:
        q = near[c]
        coal_hit = checker._run(checker._pair_pool[c], q)
        for status in (
            _kernel_level(compiled, checker, screen, k, q),
            _numpy_level(checker, screen, k, q),
        ):
            wrong_free = (status == kernels.FREE) & coal_hit
            wrong_hit = (status == kernels.COLLIDES) & ~coal_hit
            assert not wrong_free.any(), (name, checker._pairs[c], np.flatnonzero(wrong_free)[:5])
            assert not wrong_hit.any(), (name, checker._pairs[c], np.flatnonzero(wrong_hit)[:5])
            for s in decided:
                decided[s] += int((status == s).sum())
    assert decided[kernels.FREE] > 500 and decided[kernels.COLLIDES] > 100, (name, decided)


def test_kernel_decides_within_the_slack_of_numpy(compiled, case, monkeypatch):
    """The kernel's decisions lie between the NumPy level's and its with limits 2e-9 m stricter."""
    name, checker, near, _ = case
    for screen, k, c in _columns(checker):
        q = near[c]
        got = _kernel_level(compiled, checker, screen, k, q)
        loose = _numpy_level(checker, screen, k, q)
        monkeypatch.setattr(broadphase, "BROAD_MARGIN", BROAD_MARGIN + 2 * kernels.SLACK)
        monkeypatch.setattr(broadphase, "INSIDE_DEPTH", INSIDE_DEPTH + 2 * kernels.SLACK)
        strict = _numpy_level(checker, screen, k, q)
        monkeypatch.undo()
        decided = got != kernels.UNDECIDED
        assert np.array_equal(got[decided], loose[decided]), (name, checker._pairs[c])
        sure = strict != kernels.UNDECIDED
        assert np.array_equal(got[sure], strict[sure]), (name, checker._pairs[c])
        assert compiled.hull_vs_cylinder(
            np.zeros((1, 3, 4)),
            np.zeros(0, dtype=np.intp),
            *checker._compiled_screen(screen)[3][k][1:],
        ).shape == (0,)


def test_kernel_limits_are_the_numpy_ones_plus_the_slack(case):
    _, checker, _, _ = case
    for screen, k, _ in _columns(checker):
        _, verts, inv, limits = checker._compiled_screen(screen)[3][k]
        _, verts0, inv0, radius, half = screen.cylinders[k]
        np.testing.assert_array_equal(verts, verts0)
        np.testing.assert_array_equal(inv, inv0)
        np.testing.assert_array_equal(
            limits, [radius, half, BROAD_MARGIN + kernels.SLACK, INSIDE_DEPTH + kernels.SLACK]
        )


@pytest.mark.parametrize("mode", ["grasp", "approach"])
def test_same_decisions_without_the_level(case, mode, numpy_code):
    """The checker's answers equal those of the same checker with the level's columns removed."""
    assert_same_without_level(case, mode, numpy_code, {"", "collision_object"})


def test_the_vertex_box_decides_where_the_planes_do_not(compiled, case):
    """A link beside the bottle (the UR5's upper arm): the cylinder beyond a face of the box
    of its vertices. Rows free only so are free by coal, and there are many of them (on
    every robot; the fewest on the Panda).

    Independent of the levels' code: the box from the vertices, the cylinder as 2,000
    points of its surface (a solid's support is on its surface) placed in the joint's
    frame; the planes' tests as the module doc states them.
    """
    _, checker, near, _ = case
    t = np.linspace(0.0, 2.0 * np.pi, 50, endpoint=False)
    only_box = 0
    for screen, k, c in _columns(checker):
        joint, verts, inv, radius, half = screen.cylinders[k]
        q = near[c]
        status = _kernel_level(compiled, checker, screen, k, q)
        frames = checker._frames.compute(q)
        rot, pos = frames.rots[joint], frames.poss[joint]
        place = np.linalg.inv(inv)
        # the cylinder's rims and axis-parallel lines, in the base frame, then the joint's
        zs = np.linspace(-half, half, 20)
        ring = np.stack(
            np.broadcast_arrays(radius * np.cos(t)[:, None], radius * np.sin(t)[:, None], zs[None]),
            -1,
        )
        pts = ring.reshape(-1, 3) @ place[:3, :3].T + place[:3, 3]
        local = np.einsum("nji,npj->npi", rot, pts[None] - pos[:, None])  # (N, P, 3)
        lo, hi = verts.min(axis=1), verts.max(axis=1)
        beyond = (local.min(axis=1) > hi + BROAD_MARGIN) | (local.max(axis=1) < lo - BROAD_MARGIN)
        x, y, z = (
            np.einsum("ij,njv->niv", inv[:3, :3], np.einsum("nij,jv->niv", rot, verts))
            + (pos @ inv[:3, :3].T + inv[:3, 3])[:, :, None]
        ).transpose(1, 0, 2)
        caps = np.all(z > half + BROAD_MARGIN, axis=1) | np.all(z < -half - BROAD_MARGIN, axis=1)
        mid = np.stack([x.mean(1), y.mean(1)], 1)
        u = mid / np.linalg.norm(mid, axis=1, keepdims=True)
        side = np.all(u[:, :1] * x + u[:, 1:] * y > radius + BROAD_MARGIN, axis=1)
        box_only = (status == kernels.FREE) & ~caps & ~side
        assert np.all(beyond.any(axis=1)[box_only]), (
            checker._pairs[c],
            np.flatnonzero(box_only & ~beyond.any(axis=1))[:5],
        )
        assert not checker._run(checker._pair_pool[c], q[box_only]).any()
        only_box += int(box_only.sum())
    assert only_box > (10 if case[0] == "panda" else 100), only_box  # the Panda's: 19
