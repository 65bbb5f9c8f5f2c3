"""coal's distance to a cloud over the cells near a link equals coal's over the whole tile.

:func:`~gcm_pipeline.robot.collision.octree_near.near_distance` (what the clearance asks
coal for a link against an octree tile) against its reference, coal's distance of the
link to the whole tile, on Panda configurations near a cluttered cloud: equal (to
1e-9 m) wherever the whole tile's distance is below the cap, never below it elsewhere;
and the checker's clearance against the one of a checker that asks coal for whole tiles.
"""

from __future__ import annotations

import coal
import numpy as np
import pinocchio as pin
import pytest
import trimesh

from gcm_pipeline.geometry.clouds import VoxelGrid
from gcm_pipeline.robot.collision import CollisionChecker
from gcm_pipeline.robot.collision.broadphase import ShapeBound
from gcm_pipeline.robot.collision.clouds import cloud_shapes
from gcm_pipeline.robot.collision.octree_near import near_distance
from gcm_pipeline.robot.collision.pairs import coal_transform
from gcm_pipeline.robot.collision.spheres import geometry_mesh
from gcm_pipeline.robot.ik import solve_ik

VOXEL = 0.005


@pytest.fixture(scope="module")
def scene(panda):
    """Octree tiles of a table top, a box and a shelf board (5 mm voxels), and Panda
    configurations with the hand 1 to 15 cm over them."""
    rng = np.random.default_rng(4)
    top = np.column_stack([rng.uniform(0.3, 0.8, 60000), rng.uniform(-0.3, 0.3, 60000)])
    table = np.column_stack([top, rng.normal(0.0, 0.002, len(top))])
    box = trimesh.creation.box((0.1, 0.08, 0.15))
    box.apply_translation((0.55, 0.15, 0.075))
    board = trimesh.creation.box((0.2, 0.5, 0.02))
    board.apply_translation((0.75, 0.0, 0.35))
    pts = np.concatenate([table, box.sample(20000, seed=1), board.sample(20000, seed=2)])
    grid = VoxelGrid(VOXEL)
    grid.add(pts)
    centres = grid.cloud(counts={}, name="scene", source="").points
    shapes = cloud_shapes(centres, VOXEL, np.eye(4), "scene")
    targets = np.tile(np.eye(4), (80, 1, 1))
    targets[:, :3, :3] = np.diag([1.0, -1.0, -1.0])  # hand pointing down
    targets[:, :3, 3] = np.column_stack(
        [rng.uniform(0.35, 0.7, 80), rng.uniform(-0.25, 0.25, 80), rng.uniform(0.11, 0.25, 80)]
    )
    res = solve_ik(panda, targets)
    assert np.count_nonzero(res.success) > 40
    return shapes, res.q[res.success]


def _links(panda):
    """The Panda's hand and wrist geometries (those near the cloud), each with its points
    and one sphere holding them."""
    gm = panda.build_geometry("collision")
    out = []
    for g, go in enumerate(gm.geometryObjects):
        if not any(k in go.name for k in ("hand", "finger", "link6", "link7")):
            continue
        pts, tris = geometry_mesh(go.geometry)
        pts = pts[np.unique(tris)] if tris.size else pts
        centre = 0.5 * (pts.min(axis=0) + pts.max(axis=0))
        radius = float(np.sqrt(((pts - centre) ** 2).sum(axis=1).max())) + 1e-9
        out.append((g, go.geometry, pts, centre, radius))
    return gm, out


def test_near_cells_give_coal_the_whole_tile_distance_below_the_cap(panda, scene):
    shapes, qs = scene
    gm, links = _links(panda)
    data, gd = panda.model.createData(), pin.GeometryData(gm)
    bounds = [ShapeBound(s.geometry, s.placement) for s in shapes]
    eye = coal_transform(np.eye(4))
    below = above = 0
    for q in qs[:4]:
        pin.updateGeometryPlacements(panda.model, data, gm, gd, q)
        for g, geom, pts, centre, radius in links:
            m = gd.oMg[g].homogeneous
            tf = coal_transform(m)
            placed = pts @ m[:3, :3].T + m[:3, 3]
            ball = (centre @ m[:3, :3].T + m[:3, 3])[None]
            for s, b in zip(shapes, bounds, strict=True):
                req = coal.DistanceRequest()
                whole = coal.distance(geom, tf, s.geometry, eye, req, coal.DistanceResult())
                for cap in (np.inf, whole + 0.01, whole * 0.5, 0.02):
                    got = near_distance(
                        geom, tf, s.geometry, eye, b.cells, b.cell_reach,
                        ball, np.array([radius]), placed, cap, req,
                    )  # fmt: skip
                    if whole < cap:
                        assert abs(got - whole) <= 1e-9, (g, cap, got, whole)
                        below += 1
                    else:
                        assert got >= whole - 1e-9, (g, cap, got, whole)
                        above += 1
    assert below > 100 and above > 100  # both kinds of answer, many of each


def test_clearance_equals_the_one_from_whole_tiles(panda, scene):
    """Over cells near each link or over whole tiles (coal's own traversal): one answer."""
    shapes, qs = scene
    fast = CollisionChecker(panda, shapes, self_collision=False)
    whole = CollisionChecker(panda, shapes, self_collision=False)
    whole._octree_pairs = {}  # every octree pair by pin.computeDistance on the whole tile
    assert fast._octree_pairs
    for precision in (0.0, 1e-3):
        a, b = fast.clearance(qs[:20], precision), whole.clearance(qs[:20], precision)
        np.testing.assert_allclose(a, b, rtol=0, atol=1e-9)
    assert np.all(np.isfinite(a)) and np.ptp(a) > 0.05
