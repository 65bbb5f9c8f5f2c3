"""Sphere-vs-shape bounds of the broad phase, against coal's distance, for every world shape kind.

The broad phase rules a robot sphere out against a world shape when
:meth:`ShapeBound.lower` of its centre, less its radius, exceeds the margin.
That is sound only if the bound never exceeds the true distance: checked here
against ``coal.distance`` of the placed sphere and shape, for the primitives
(where the bound is exact: equal to coal's distance) and for the shapes bounded
by their local box (a cone, an ellipsoid, a convex polytope, a triangle mesh).
The compiled kernel's packed form of the same bound is compared with it.

Then on robots, for the Panda, the UR5 with the Robotiq 2F-85 and a user URDF
(``write_mixed_arm``): every cover sphere and ball of the checker, placed by its
joint frames in configurations on both sides of contact, against every world
shape it is checked against (the table, the bottle, the bottle shrunk by the
contact tolerance); and, per checked pair, the spheres' bound against coal's
distance of the link's own geometry (placed by Pinocchio) and the shape.
"""

from __future__ import annotations

import coal
import numpy as np
import pinocchio as pin
import pytest
import trimesh
from helpers import around_the_bottle, decision_contact, random_rigid
from urdfs import bottle_checker

from gcm_pipeline.geometry.meshes import read_mesh
from gcm_pipeline.robot import kernels
from gcm_pipeline.robot.collision.broadphase import ShapeBound


def _mesh(kind: str, folder):
    """An elongated blob (its box is loose at the corners): a convex polytope, or a
    triangle mesh read from an OBJ file as a world mesh is."""
    mesh = trimesh.creation.icosphere(subdivisions=2, radius=0.08)
    mesh.vertices *= [1.0, 0.6, 1.8]
    if kind == "convex":
        vec = coal.StdVec_Vec3s()
        for p in np.asarray(mesh.vertices, float):
            vec.append(p)
        return coal.Convex.convexHull(vec, False, None)
    path = folder / "blob.obj"
    mesh.export(path)
    return read_mesh(path)


#: World shapes and whether the bound is exact (a primitive) or a box around the shape.
SHAPES = {
    "sphere": (lambda d: coal.Sphere(0.07), True),
    "box": (lambda d: coal.Box(0.3, 0.12, 0.05), True),
    "cylinder": (lambda d: coal.Cylinder(0.04, 0.22), True),
    "capsule": (lambda d: coal.Capsule(0.05, 0.2), True),
    "cone": (lambda d: coal.Cone(0.06, 0.2), False),
    "ellipsoid": (lambda d: coal.Ellipsoid(0.1, 0.05, 0.03), False),
    "convex polytope": (lambda d: _mesh("convex", d), False),
    "triangle mesh": (lambda d: _mesh("bvh", d), False),
}


def _coal_distance(geometry, placement: np.ndarray, centre: np.ndarray, radius: float) -> float:
    req, res = coal.DistanceRequest(), coal.DistanceResult()
    return coal.distance(
        geometry,
        coal.Transform3s(placement[:3, :3], placement[:3, 3]),
        coal.Sphere(radius),
        coal.Transform3s(np.eye(3), centre),
        req,
        res,
    )


def _packed_lower(row: np.ndarray, points: np.ndarray) -> np.ndarray:
    """The compiled kernel's bound, one point at a time through its scalar helper."""
    from gcm_pipeline.robot.collision.broadphase_kernel import _lower

    return np.array([_lower(p, row) for p in points])


@pytest.mark.parametrize("kind", list(SHAPES))
def test_sphere_bound_never_exceeds_coal_distance(kind, tmp_path):
    """For 400 spheres around and through each shape: ``lower(centre) - r <= distance``;
    exact (equal to coal's distance) for the primitives; never vacuous."""
    make, exact = SHAPES[kind]
    rng = np.random.default_rng(sum(map(ord, kind)))
    geometry, placement = make(tmp_path), random_rigid(rng, 0.3)
    bound = ShapeBound(geometry, placement)
    assert bound.exact == exact
    # centres in a shell from inside the shape to 20 cm outside, radii 0-4 cm
    centres = placement[:3, 3] + rng.normal(0.0, 0.15, (400, 3))
    radii = rng.uniform(0.0, 0.04, 400)
    lower = bound.lower(centres) - radii
    true = np.array(
        [_coal_distance(geometry, placement, c, r) for c, r in zip(centres, radii, strict=True)]
    )
    apart = true > 1e-9  # coal's distance is negative or 0 for overlapping shapes
    assert apart.sum() > 100 and (~apart).sum() > 5  # both sides are sampled
    # sound: a sphere the bound rules out is apart by at least the bound
    assert np.all(lower[apart] <= true[apart] + 1e-9)
    assert np.all(lower[~apart] <= 1e-9)  # an overlapping sphere is never ruled out
    if exact:
        np.testing.assert_allclose(lower[apart], true[apart], atol=1e-6)
    else:
        assert np.mean(lower[apart] > 0) > 0.5  # the box bound still rules most out
    if kernels.get() is not None:
        # the compiled kernel's packed bound is the same bound
        packed = _packed_lower(bound.packed(), centres)
        np.testing.assert_allclose(packed, bound.lower(centres), atol=1e-12)


def _placed(frames, joints, local):
    """Points (N, P, 3) [m] of ``local`` (P, 3) fixed to ``joints`` (P,), base frame."""
    rots, poss = np.stack(frames.rots, 1)[:, joints], np.stack(frames.poss, 1)[:, joints]
    return np.einsum("npij,pj->npi", rots, local) + poss


@pytest.mark.parametrize("name", ["panda", "ur5_robotiq", "user_mixed"])
def test_robot_spheres_bounds_near_contact(name, tmp_path):
    """The bound of each placed cover sphere and ball is coal's distance to the shape (to
    1e-6 m where apart, never above 0 where they overlap), and, pair by pair, the least
    of a link's spheres' bounds never exceeds coal's distance of the link itself."""
    checker = bottle_checker(name, tmp_path)
    robot, gm, cov = checker.robot, checker._gm, checker._cover
    q = np.concatenate([robot.random_configurations(150, 31), around_the_bottle(robot, 150, 32)])
    q = np.concatenate([q, decision_contact(checker, q, "grasp", most=150)])
    frames = checker._frames.compute(q)
    world = sorted({p.b for p in checker._pairs if p.kind != "self"})
    assert {type(gm.geometryObjects[w].geometry) for w in world} == {coal.Box, coal.Cylinder}
    n_robot = len(cov.start) - 1
    # every placed sphere, (N, S, 3), and ball, (N, R, 3)
    centres = _placed(frames, cov.joint, cov.centre)
    balls = _placed(frames, cov.ball_joint, cov.ball_centre)
    rows = np.random.default_rng(2).choice(len(q), 40, replace=False)
    for w in world:
        shape = gm.geometryObjects[w]
        bound = ShapeBound(shape.geometry, shape.placement.homogeneous)
        assert bound.exact
        for pts, radii in ((centres, cov.radius), (balls, cov.ball_radius)):
            lower = bound.lower(pts[rows].reshape(-1, 3)) - np.tile(radii, rows.size)
            true = np.array(
                [
                    _coal_distance(shape.geometry, shape.placement.homogeneous, c, r)
                    for c, r in zip(
                        pts[rows].reshape(-1, 3), np.tile(radii, rows.size), strict=True
                    )
                ]
            )
            apart = true > 1e-9
            assert apart.sum() > 100 and (~apart).sum() > 5, (name, shape.name)
            np.testing.assert_allclose(lower[apart], true[apart], atol=1e-6)
            assert np.all(lower[~apart] <= 1e-9), (name, shape.name)
    # pair by pair: the spheres' least bound against the link's own distance
    data, gd = robot.model.createData(), pin.GeometryData(gm)
    req = coal.DistanceRequest()
    tight = 0
    for i in rows:
        pin.updateGeometryPlacements(robot.model, data, gm, gd, q[i])
        for p in checker._pairs:
            if p.kind == "self" or p.owner >= n_robot:
                continue
            shape = gm.geometryObjects[p.b]
            e = slice(cov.start[p.owner], cov.start[p.owner + 1])
            least = (checker._bounds[p.b].lower(centres[i, e]) - cov.radius[e]).min()
            d = coal.distance(
                gm.geometryObjects[p.a].geometry,
                coal.Transform3s(gd.oMg[p.a].homogeneous[:3, :3], gd.oMg[p.a].translation),
                shape.geometry,
                coal.Transform3s(shape.placement.homogeneous[:3, :3], shape.placement.translation),
                req,
                coal.DistanceResult(),
            )
            assert least <= max(d, 0.0) + 1e-9, (name, shape.name, gm.geometryObjects[p.a].name)
            tight += int(d - 0.01 < least < d + 1e-9)
    assert tight > 50, (name, tight)  # bounds within 1 cm of the distance are common
