"""Sphere-vs-shape bounds of the broad phase, against coal's distance, for every world shape kind.

The broad phase rules a robot sphere out against a world shape when
:meth:`ShapeBound.lower` of its centre, less its radius, exceeds the margin.
That is sound only if the bound never exceeds the true distance: checked here
against ``coal.distance`` of the placed sphere and shape, for the primitives
(where the bound is exact: equal to coal's distance) and for the shapes bounded
by their local box (a cone, an ellipsoid, a convex polytope, a triangle mesh).
The compiled kernel's packed form of the same bound is compared with it.
"""

from __future__ import annotations

import coal
import numpy as np
import pytest
import trimesh
from helpers import random_rigid

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
