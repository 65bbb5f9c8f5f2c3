"""Point clouds as obstacles: octree tiles, their broad-phase bound, the checker against coal."""

from __future__ import annotations

import coal
import numpy as np
import pinocchio as pin
import pytest
import trimesh
from helpers import complete_answers

from gcm_pipeline.geometry.clouds import VoxelGrid
from gcm_pipeline.robot.collision import CollisionChecker
from gcm_pipeline.robot.collision.broadphase import ShapeBound, octree_box
from gcm_pipeline.robot.collision.clouds import cloud_shapes, octree, tiles, within_distance
from gcm_pipeline.robot.collision.pairs import se3
from gcm_pipeline.robot.collision.world import object_shape
from gcm_pipeline.robot.ik import solve_ik

pytestmark = pytest.mark.usefixtures("kernels_on")

VOXEL = 0.01


def _clutter_points(seed: int = 0) -> np.ndarray:
    """Surface points of a box, a cylinder and a sphere in front of the Panda [m]."""
    box = trimesh.creation.box((0.08, 0.06, 0.25))
    box.apply_translation((0.5, 0.18, 0.125))
    cyl = trimesh.creation.cylinder(0.04, 0.3)
    cyl.apply_translation((0.45, -0.2, 0.15))
    ball = trimesh.creation.icosphere(3, 0.06)
    ball.apply_translation((0.62, 0.0, 0.35))
    return np.concatenate([m.sample(8000, seed=seed + i) for i, m in enumerate((box, cyl, ball))])


@pytest.fixture(scope="module")
def clutter():
    """Voxel centres of the clutter (1 cm) and its octree tiles in the Panda's base frame."""
    grid = VoxelGrid(VOXEL)
    grid.add(_clutter_points())
    centres = grid.cloud(counts={}, name="cloud", source="").points
    return centres, cloud_shapes(centres, VOXEL, np.eye(4), "cloud")


def _coal_distance(geom, point):
    req, res = coal.DistanceRequest(), coal.DistanceResult()
    return coal.distance(
        geom,
        coal.Transform3s(np.eye(3), np.zeros(3)),
        coal.Sphere(0.0),
        coal.Transform3s(np.eye(3), np.asarray(point, float)),
        req,
        res,
    )


def test_voxels_are_the_octree_cells_of_the_raw_points():
    """The voxel centres give coal the same occupied cells as the raw points."""
    pts = _clutter_points(3)
    for size in (0.01, 0.0073):
        grid = VoxelGrid(size)
        for part in np.array_split(pts, 7):  # chunk by chunk
            grid.add(part)
        centres = grid.cloud(counts={}, name="c", source="").points

        def cells(p, size=size):
            b = np.array([np.asarray(x)[:3] for x in octree(p, size).toBoxes()])
            return b[np.lexsort(b.T)]

        np.testing.assert_array_equal(cells(centres), cells(pts))


def test_tiles_split_the_cloud_and_their_boxes_hold_every_cell(clutter):
    centres, shapes = clutter
    parts = tiles(centres, VOXEL)
    assert 1 < len(parts) <= 16
    assert sorted(np.concatenate(parts).tolist()) == list(range(len(centres)))
    for s in shapes:
        lo, hi = octree_box(s.geometry)
        cells = np.array([np.asarray(x) for x in s.geometry.toBoxes()])
        assert np.all(cells[:, :3] - cells[:, 3:4] / 2 >= lo)
        assert np.all(cells[:, :3] + cells[:, 3:4] / 2 <= hi)


def test_octree_bound_never_exceeds_coal_distance_and_beats_the_whole_box(clutter):
    """Sound: the bound <= coal's distance near the cloud; useful: tighter than one box."""
    centres, shapes = clutter
    rng = np.random.default_rng(1)
    probe = centres[rng.integers(0, len(centres), 600)] + rng.normal(0, 0.05, (600, 3))
    tiled = np.full(len(probe), np.inf)
    for s in shapes:
        lower = ShapeBound(s.geometry, s.placement).lower(probe)
        exact = np.array([_coal_distance(s.geometry, p) for p in probe])
        assert np.all(lower <= np.maximum(exact, 0.0) + 1e-9)
        tiled = np.minimum(tiled, lower)
    lo, hi = octree_box(octree(centres, VOXEL))  # one box around the whole cloud
    whole = np.linalg.norm(np.maximum(np.maximum(lo - probe, probe - hi), 0.0), axis=1)
    assert np.all(tiled >= whole - 1e-12)
    assert np.count_nonzero(tiled > whole + 0.01) > 100  # most probes: clearly tighter
    # the cells bound tighter than the tiles' boxes: within a voxel's diagonal of coal's
    exact = np.min([[_coal_distance(s.geometry, p) for p in probe] for s in shapes], axis=0)
    outside = exact > 0
    assert np.all(exact[outside] - tiled[outside] <= VOXEL * np.sqrt(3) + 1e-6)


@pytest.fixture(scope="module")
def near_cloud(panda, clutter):
    """Panda configurations near the clutter: IK of hand poses by cloud points, perturbed."""
    centres, _ = clutter
    rng = np.random.default_rng(2)
    picks = centres[rng.integers(0, len(centres), 300)]
    targets = np.tile(np.eye(4), (300, 1, 1))
    targets[:, :3, :3] = np.diag([1.0, -1.0, -1.0])  # hand pointing down
    targets[:, :3, 3] = picks + np.array([0.0, 0.0, 0.12]) + rng.normal(0, 0.03, (300, 3))
    res = solve_ik(panda, targets)
    seeds = res.q[res.success]
    assert len(seeds) > 100
    near = [seeds + rng.normal(0.0, s, (4, *seeds.shape)) for s in (0.02, 0.1)]
    lo, hi = panda.lower, panda.upper
    qs = np.concatenate([seeds, *[x.reshape(-1, panda.nq) for x in near]])
    return np.clip(qs, lo, hi)


def _coal_reference(robot, centres, qs):
    """Whether each configuration's robot geometry collides with one octree of the cloud."""
    model = robot.model
    gm = robot.build_geometry("collision")
    n = gm.ngeoms
    tree = octree(centres, VOXEL)
    w = gm.addGeometryObject(pin.GeometryObject("cloud", 0, 0, se3(np.eye(4)), tree))
    for i in range(n):
        gm.addCollisionPair(pin.CollisionPair(i, w))
    data, gd = model.createData(), complete_answers(pin.GeometryData(gm))
    return np.array([pin.computeCollisions(model, data, gm, gd, q, False) for q in qs])


def test_checker_equals_coal_on_configurations_near_the_cloud(
    panda, clutter, near_cloud, numpy_code
):
    centres, shapes = clutter
    checker = CollisionChecker(panda, shapes, self_collision=False)
    want = _coal_reference(panda, centres, near_cloud)
    got = checker.check(near_cloud) == "collision_environment"
    assert not np.any(want & ~got), "a configuration the cloud blocks was called free"
    assert np.count_nonzero(got != want) <= 1e-3 * len(want)
    assert 0.1 < want.mean() < 0.9  # both kinds, many of each
    ref = numpy_code(checker.check, near_cloud) == "collision_environment"
    np.testing.assert_array_equal(ref, got)  # the kernels and the NumPy broad phase


def test_clearance_is_the_distance_to_the_cloud(panda, clutter, near_cloud):
    centres, shapes = clutter
    checker = CollisionChecker(panda, shapes, self_collision=False)
    free = near_cloud[checker.check(near_cloud) == ""][:20]
    got = checker.clearance(free)
    model, gm = panda.model, panda.build_geometry("collision")
    n = gm.ngeoms
    w = gm.addGeometryObject(
        pin.GeometryObject("cloud", 0, 0, se3(np.eye(4)), octree(centres, VOXEL))
    )
    for i in range(n):
        gm.addCollisionPair(pin.CollisionPair(i, w))
    data, gd = model.createData(), pin.GeometryData(gm)
    for q, c in zip(free, got, strict=True):
        pin.computeDistances(model, data, gm, gd, q)
        d = min(r.min_distance for r in gd.distanceResults)
        assert d - 1e-6 <= c <= d + 1e-3 + 1e-6  # clearance's stated precision


def test_points_within_distance_of_the_object():
    cyl = object_shape("cylinder", _Dims(0.05, 0.2), np.eye(4), np.eye(4))
    pts = np.array([[0.0, 0.0, 0.1], [0.055, 0, 0.1], [0.07, 0, 0.1], [0, 0, 0.21], [0, 0, 0.3]])
    np.testing.assert_array_equal(within_distance(cyl, pts, 0.01), [True, True, False, True, False])


class _Dims:
    def __init__(self, radius, height):
        self.radius, self.height, self.size = radius, height, None
