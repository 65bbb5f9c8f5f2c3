"""The convex-hull pre-check of mesh pairs never changes an answer.

:meth:`BroadPhase._narrow` checks a pair with a robot mesh first on the convex
hulls of its meshes (:func:`~gcm_pipeline.robot.collision.pairs.hull_pair_pool`)
and runs coal on the meshes only where the hulls touch. On configurations near
contact (random ones and, bisected between a free and a colliding one to within
1e-4 of the boundary, both sides kept) for the Panda, the UR5 with the Robotiq
2F-85 and a user URDF (a concave mesh forearm, cylinders elsewhere) in the
bottle's world, every decision of :meth:`CollisionChecker.check` in the three modes
equals the same checker's with the pre-check off (coal on the meshes for every
open entry); and the hull pools find no configuration free that coal finds
colliding on the meshes.
"""

from __future__ import annotations

import coal
import numpy as np
import pytest
import trimesh
from helpers import ROOT
from scipy.spatial import ConvexHull
from urdfs import bottle_checker, write_arm

from gcm_pipeline import pipeline as P
from gcm_pipeline.config import load_config
from gcm_pipeline.pipeline import make_checker
from gcm_pipeline.robot.collision.checker import CollisionChecker
from gcm_pipeline.robot.collision.contact import mesh_arrays
from gcm_pipeline.robot.collision.pairs import PIECES, convex_hull, hull_pair_pool, hull_pieces
from gcm_pipeline.robot.collision.world import WorldShape

#: Each test starts with the kernels on, whatever the environment says.
pytestmark = pytest.mark.usefixtures("kernels_on")

_ROBOTS = ("panda", "ur5_robotiq", "user_arm")


def _checker(name, tmp_path_factory):
    return bottle_checker(name, tmp_path_factory.mktemp("arm"))


def _without_precheck(checker, q, mode="grasp", carried=None):
    """The checker's answer with coal on the meshes for every open entry (no hulls)."""
    checker._narrow = lambda c, rows: checker._run(checker._pair_pool[c], rows)
    try:
        return checker.check(q, mode, carried)
    finally:
        del checker._narrow


def _near_contact(checker, n=600, steps=14):
    """Random configurations and, bisected from free to colliding pairs, both sides of contact."""
    q = checker.robot.random_configurations(n, 11)
    hit = _without_precheck(checker, q) != ""
    free, coll = q[~hit], q[hit]
    m = min(len(free), len(coll), 200)
    assert m > 20, (len(free), len(coll))
    a, b = free[:m].copy(), coll[:m].copy()  # a free, b colliding
    for _ in range(steps):
        mid = 0.5 * (a + b)
        mh = _without_precheck(checker, mid) != ""
        b[mh], a[~mh] = mid[mh], mid[~mh]
    return np.concatenate([q, a, b])


@pytest.fixture(scope="module", params=_ROBOTS)
def case(request, tmp_path_factory):
    checker = _checker(request.param, tmp_path_factory)
    assert checker.static_collisions == ()
    return checker, _near_contact(checker)


@pytest.mark.parametrize("mode", ["grasp", "approach", "retreat"])
def test_same_decisions_as_without_the_precheck(compiled, case, mode, numpy_code):
    checker, q = case
    carried = None
    if mode == "retreat":  # the object held 12 cm ahead of the grasp frame
        carried = np.eye(4)
        carried[2, 3] = 0.12
    got = checker.check(q, mode, carried)
    np.testing.assert_array_equal(got, _without_precheck(checker, q, mode, carried))
    kinds = set(np.unique(got).tolist())
    assert "" in kinds and len(kinds) >= 2
    # the NumPy broad phase reaches coal through the same pre-check
    ref = numpy_code(checker.check, q, mode, carried)
    np.testing.assert_array_equal(ref, got)
    # the pre-check ran: some pair reached coal through a hull pool
    assert any(pool is not None for pool in checker._hull_pools.values())


def test_hull_apart_only_where_meshes_apart(case):
    """Pair by pair, 0 configurations with the hulls apart and the meshes colliding.

    Every pair that has a hull pool, on every configuration (no broad phase),
    so both sides of the hull margin are sampled; and the hulls do rule some
    configurations out (the pre-check does work).
    """
    checker, q = case
    pooled = 0
    ruled_out = 0
    by_pieces = 0  # configurations the pieces rule out where the whole hulls touch
    for c, pair in enumerate(checker._pairs):
        pool = hull_pair_pool(checker._model, checker._gm, pair, 1, {})
        if pool is None:
            continue
        pooled += 1
        hull_hit = checker._run(pool, q)
        mesh_hit = checker._run(checker._pair_pool[c], q)
        assert not np.any(mesh_hit & ~hull_hit), (pair, np.flatnonzero(mesh_hit & ~hull_hit))
        ruled_out += int(np.count_nonzero(~hull_hit))
        pieces = hull_pair_pool(checker._model, checker._gm, pair, 1, {}, PIECES)
        if pieces is not None:
            piece_hit = checker._run(pieces, q)
            assert not np.any(mesh_hit & ~piece_hit), (pair, np.flatnonzero(mesh_hit & ~piece_hit))
            assert not np.any(piece_hit & ~hull_hit), pair  # the pieces lie in the hull
            by_pieces += int(np.count_nonzero(hull_hit & ~piece_hit))
    assert pooled > 0 and ruled_out > 0
    if checker.robot.name == "ur5":  # its forearm's pieces beside the bottle
        assert by_pieces > 0


@pytest.mark.parametrize("name", _ROBOTS)
def test_hull_pieces_hold_every_triangle(name, tmp_path_factory):
    """Each triangle of a robot mesh lies in the hull of one of its pieces (1e-9 m)."""
    checker = _checker(name, tmp_path_factory)
    cut = 0
    for go in list(checker._gm.geometryObjects)[: checker.n_robot_geoms]:
        pieces = hull_pieces(go.geometry)
        if pieces is None:
            continue
        verts, tris = mesh_arrays(go.geometry)
        held = np.zeros(len(tris), dtype=bool)
        for piece in pieces:
            planes = ConvexHull(np.array(piece.points(), dtype=float).reshape(-1, 3)).equations
            inside = (verts @ planes[:, :3].T + planes[:, 3] <= 1e-9).all(axis=1)
            held |= inside[tris].all(axis=1)
        assert held.all(), (name, go.name, np.flatnonzero(~held)[:5])
        cut += len(pieces) > 1
    assert cut > 0 or name == "user_arm"  # its concave forearm has a flat piece: whole


def test_a_flat_mesh_is_checked_without_a_hull(tmp_path):
    """A robot link whose mesh is flat (a plate of two triangles) gets no hull (coal crashed
    building it) and its pairs the same answers as coal's on the meshes."""
    plate = trimesh.Trimesh(
        [[-0.05, -0.05, 0.0], [0.05, -0.05, 0.0], [0.05, 0.05, 0.0], [-0.05, 0.05, 0.0]],
        [[0, 1, 2], [0, 2, 3]],
        process=False,
    )
    (tmp_path / "meshes").mkdir()
    plate.export(tmp_path / "meshes" / "plate.stl")
    spec = write_arm(tmp_path, mesh="meshes/plate.stl", mesh_link="wrist_3_link")
    cfg = load_config(ROOT / "configs" / "bottle_side.yaml", [f"robot.spec={spec}"])
    checker = make_checker(P.robot_from_config(cfg), cfg.environment, cfg.object)
    flat = [
        go.geometry
        for go in checker._gm.geometryObjects
        if isinstance(go.geometry, coal.BVHModelBase) and go.name.startswith("wrist_3")
    ]
    assert flat and convex_hull(flat[0]) is None and hull_pieces(flat[0]) is None
    q = checker.robot.random_configurations(2000, 2)
    got = checker.check(q)
    np.testing.assert_array_equal(got, _without_precheck(checker, q))
    assert "" in set(got.tolist()) and len(set(got.tolist())) >= 2


def test_no_hull_pool_against_a_world_mesh_or_cloud():
    """A robot mesh against a world mesh or point cloud gets no hull pool; a primitive does."""
    cfg = load_config(ROOT / "configs" / "bottle_side.yaml")
    robot = P.robot_from_config(cfg)
    box = coal.Box(0.1, 0.1, 0.1)
    mesh = coal.BVHModelOBBRSS()
    verts = np.array([[0, 0, 0], [0.1, 0, 0], [0, 0.1, 0], [0, 0, 0.1]], dtype=float)
    tris = np.array([[0, 1, 2], [0, 1, 3], [0, 2, 3], [1, 2, 3]], dtype=np.int32)
    mesh.beginModel(len(tris), len(verts))
    mesh.addVertices(verts)
    mesh.addTriangles(tris)
    mesh.endModel()
    cloud = coal.makeOctree(np.random.default_rng(0).uniform(-0.05, 0.05, (200, 3)), 0.01)
    place = np.eye(4)
    place[:3, 3] = [0.5, 0.0, 0.3]
    world = [
        WorldShape("box", box, place, "environment"),
        WorldShape("tet", mesh, place, "environment"),
        WorldShape("cloud", cloud, place, "environment"),
    ]
    checker = CollisionChecker(robot, world)
    names = [go.name for go in checker._gm.geometryObjects]
    geoms = checker._gm.geometryObjects
    meshes = [g for g in range(checker.n_robot_geoms) if convex_hull(geoms[g].geometry) is not None]
    assert meshes
    pools = {}
    for pair in checker._pairs:
        if pair.kind == "environment" and pair.a in meshes:
            pool = hull_pair_pool(checker._model, checker._gm, pair, 1, {})
            pools.setdefault(names[pair.b], []).append(pool)
    assert all(p is None for p in pools["tet"]) and pools["tet"]
    assert all(p is None for p in pools["cloud"]) and pools["cloud"]
    assert all(p is not None for p in pools["box"]) and pools["box"]
