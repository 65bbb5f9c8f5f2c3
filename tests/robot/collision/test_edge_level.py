"""Level 4 of the broad phase: a robot polytope's edges inside a world primitive.

An edge of a mesh's (or a convex piece's, or a box's) triangles lies on the
geometry coal checks, so a point of it deeper than ``INSIDE_DEPTH`` inside a
table, a box obstacle, a sphere or a cylinder (the bottle) is a contact: the
pair collides without calling coal. Checked here:

* the geometry of :func:`segments_inside` (NumPy) and of the compiled
  ``edges_inside`` against points sampled along each segment, for random
  segments through a box, a sphere and a cylinder;
* pair by pair, on random configurations of the Panda and the UR5 with its
  2F-85 in the bottle's world: every (pair, configuration) level 4 calls
  colliding, coal (as the checker asks it) calls colliding too, and level 4
  does decide some;
* the checker's decisions in the three modes with level 4 equal those
  without it (the decisions near contact against an independent
  implementation of the rules are in ``test_near_contact.py``).
"""

from __future__ import annotations

import coal
import numpy as np
import pytest
from helpers import ROOT, random_rigid

from gcm_pipeline import pipeline as P
from gcm_pipeline.config import load_config
from gcm_pipeline.pipeline import make_checker
from gcm_pipeline.robot.collision import broadphase
from gcm_pipeline.robot.collision.broadphase import INSIDE_DEPTH, ShapeBound, segments_inside
from gcm_pipeline.robot.collision.pairs import MODE_BIT

#: Each test starts with the kernels on, whatever the environment says.
pytestmark = pytest.mark.usefixtures("kernels_on")

_SHAPES = {
    "box": lambda: coal.Box(0.3, 0.2, 0.05),
    "sphere": lambda: coal.Sphere(0.08),
    "cylinder": lambda: coal.Cylinder(0.04, 0.22),
}


def _sampled_depth(bound, points):
    """How deep points (..., 3) in the shape's frame lie inside it (< 0: outside) [m]."""
    x, y, z = points[..., 0], points[..., 1], points[..., 2]
    if bound.kind == "box":
        return np.min(bound.halfs - np.abs(points - bound.centre), axis=-1)
    if bound.kind == "sphere":
        return bound.radius - np.sqrt(x * x + y * y + z * z)
    return np.minimum(bound.radius - np.sqrt(x * x + y * y), bound.half - np.abs(z))


@pytest.mark.parametrize("kind", list(_SHAPES))
def test_segments_inside_geometry(compiled, kind):
    """Segments (M rows of E) through, near and beside the shape: the NumPy and compiled
    answers agree with points sampled along them, and with each other."""
    rng = np.random.default_rng(len(kind))
    placement = random_rigid(rng)
    bound = ShapeBound(_SHAPES[kind](), placement)
    m, e = 500, 4
    centre = placement[:3, 3]
    a = centre + rng.normal(0.0, 0.15, (m, e, 3))
    b = a + rng.normal(0.0, 0.12, (m, e, 3))
    b[:, 0] = a[:, 0]  # a point
    b[:, 1, :2] = a[:, 1, :2]  # vertical (the cylinder's axis is tilted: a general line)
    inv = np.linalg.inv(placement)
    local_a = (a @ inv[:3, :3].T + inv[:3, 3]).transpose(0, 2, 1)  # (M, 3, E)
    local_b = (b @ inv[:3, :3].T + inv[:3, 3]).transpose(0, 2, 1)
    got = segments_inside(local_a, local_b, bound.packed(), INSIDE_DEPTH)
    # points along each segment, 4001 of them: one deeper than the depth means inside
    t = np.linspace(0.0, 1.0, 4001)[:, None, None]
    la, lb = local_a.transpose(0, 2, 1), local_b.transpose(0, 2, 1)
    depth = np.array([_sampled_depth(bound, la[i] + t * (lb[i] - la[i])).max() for i in range(m)])
    assert np.all(got[depth > INSIDE_DEPTH + 1e-6])  # a sampled point inside: inside
    assert not np.any(got[depth < INSIDE_DEPTH - 1e-3])  # every point shallow or outside
    assert 50 < got.sum() < m - 50
    # the compiled kernel: the ends in a joint's frame placed at the identity
    tfs = np.tile(np.eye(4)[:3], (m, 1, 1))
    rows = np.arange(m)
    inside = np.zeros(m, dtype=bool)
    for k in range(e):  # one edge per call: row i's edge k
        pa = np.ascontiguousarray(a[:, k].T)
        pb = np.ascontiguousarray(b[:, k].T)
        for i in range(m):  # each row its own edge: a frame per row would do the same
            one = compiled.edges_inside(
                tfs[i : i + 1], rows[:1], pa[:, i : i + 1], pb[:, i : i + 1], bound.packed(),
                INSIDE_DEPTH,
            )  # fmt: skip
            inside[i] |= bool(one[0])
    strict = segments_inside(local_a, local_b, bound.packed(), INSIDE_DEPTH + 1e-9)
    loose = segments_inside(local_a, local_b, bound.packed(), INSIDE_DEPTH - 1e-9)
    assert np.all(inside[strict]) and not np.any(inside[~loose])


def _robot_checker(name):
    cfg = load_config(ROOT / "configs" / name)
    robot = P.robot_from_config(cfg)
    return make_checker(robot, cfg.environment, cfg.object)


@pytest.fixture(scope="module", params=["bottle_side.yaml", "bottle_side_ur5.yaml"])
def world(request):
    checker = _robot_checker(request.param)
    q = checker.robot.random_configurations(1500, 5)
    return request.param, checker, q


def test_edges_inside_only_where_coal_collides(compiled, world):
    """Pair by pair, every configuration: level 4's 'collides' is coal's too; it decides some."""
    name, checker, q = world
    frames = checker._frames.compute(q)
    tfs = broadphase.stacked(frames.transforms)
    decided = 0
    for bit in (MODE_BIT["grasp"], MODE_BIT["approach"]):
        screen = checker._screens[bit]
        _, _, edges, _, _ = checker._compiled_screen(screen)
        assert edges, name  # meshes against the table and the bottle
        for k, (joint, *ends) in edges.items():
            inside = compiled.edges_inside(tfs[joint], np.arange(len(q)), *ends)
            if inside.any():
                c = int(screen.pairs[k])
                coal_hit = checker._run(checker._pair_pool[c], q[inside])
                assert coal_hit.all(), (name, checker._pairs[c], np.flatnonzero(~coal_hit)[:5])
                decided += int(inside.sum())
    assert decided > 50, name


@pytest.mark.parametrize("mode", ["grasp", "approach", "retreat"])
def test_same_decisions_without_level_4(world, mode, numpy_code, monkeypatch):
    """The checker's answers with level 4 equal those of a checker built without it."""
    name, checker, q = world
    monkeypatch.setattr(broadphase, "EDGE_SHAPES", ())
    plain = _robot_checker(name)
    monkeypatch.undo()
    assert not any(plain._screens[b].edges for b in plain._screens)
    carried = None
    if mode == "retreat":  # the object held 12 cm ahead of the grasp frame
        carried = np.eye(4)
        carried[2, 3] = 0.12
    got = checker.check(q, mode, carried)
    np.testing.assert_array_equal(got, plain.check(q, mode, carried))
    np.testing.assert_array_equal(numpy_code(checker.check, q, mode, carried), got)
    assert len(set(got.tolist())) >= 3
