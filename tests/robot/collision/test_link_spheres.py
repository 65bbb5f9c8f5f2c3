"""Sphere models contain their links: every sampled point of each collision geometry.

Two models, for the Panda, the UR5 with the Robotiq 2F-85 and a user URDF
(``write_mixed_arm``: cylinders, a sphere, boxes, a concave and a convex STL
mesh): the outer link spheres (:mod:`~gcm_pipeline.robot.collision.link_spheres`)
in each parent joint's frame, and the checker's own broad-phase covers (a few
spheres per geometry and one ball around them,
:func:`~gcm_pipeline.robot.collision.spheres.robot_covers`) placed by the
checker's joint frames, against the geometry placed by Pinocchio.

The points are sampled independently of the generator (its own seed, the
geometry's exact surface, not the meshes the generator covers): uniformly on
each geometry's surface (a mesh's triangles, a box's faces, a cylinder's side
and caps, a sphere's or a capsule's surface), plus every mesh vertex and
points inside the solid primitives, mapped into the parent joint's frame with
the geometry's placement.
"""

from __future__ import annotations

import coal
import numpy as np
import pinocchio as pin
import pytest
from urdfs import bottle_checker, write_mixed_arm

from gcm_pipeline.config.robot_spec import load_robot
from gcm_pipeline.robot.collision.contact import mesh_arrays
from gcm_pipeline.robot.collision.link_spheres import geometry_spheres, link_spheres, sphere_counts


def _unit(rng: np.random.Generator, n: int) -> np.ndarray:
    d = rng.normal(size=(n, 3))
    return d / np.linalg.norm(d, axis=1, keepdims=True)


def _triangles(v: np.ndarray, t: np.ndarray, n: int, rng: np.random.Generator) -> np.ndarray:
    a, b, c = v[t[:, 0]], v[t[:, 1]], v[t[:, 2]]
    area = 0.5 * np.linalg.norm(np.cross(b - a, c - a), axis=1)
    pick = rng.choice(len(t), size=n, p=area / area.sum())
    u, w = rng.random((2, n))
    flip = u + w > 1
    u[flip], w[flip] = 1 - u[flip], 1 - w[flip]
    return a[pick] + u[:, None] * (b - a)[pick] + w[:, None] * (c - a)[pick]


def surface_points(geometry, n: int, rng: np.random.Generator) -> np.ndarray:
    """Points of a coal geometry (its own frame): its surface, vertices, and inside."""
    if isinstance(geometry, coal.Sphere):
        r = geometry.radius
        return np.vstack([r * _unit(rng, n), r * rng.random((n, 1)) ** (1 / 3) * _unit(rng, n)])
    if isinstance(geometry, coal.Capsule):
        r, h = geometry.radius, geometry.halfLength
        ang = rng.uniform(0, 2 * np.pi, n)
        side = np.column_stack([r * np.cos(ang), r * np.sin(ang), rng.uniform(-h, h, n)])
        caps = r * _unit(rng, n)
        caps[:, 2] += np.where(caps[:, 2] >= 0, h, -h)
        return np.vstack([side, caps])
    if isinstance(geometry, coal.Cylinder):
        r, h = geometry.radius, geometry.halfLength
        ang = rng.uniform(0, 2 * np.pi, (2, n))
        side = np.column_stack([r * np.cos(ang[0]), r * np.sin(ang[0]), rng.uniform(-h, h, n)])
        rho = r * np.sqrt(rng.random(n))
        caps = np.column_stack([rho * np.cos(ang[1]), rho * np.sin(ang[1]), rng.choice([-h, h], n)])
        return np.vstack([side, caps, [[r, 0, h], [-r, 0, -h], [0, r, h]]])
    if isinstance(geometry, coal.Box):
        half = np.asarray(geometry.halfSide)
        p = rng.uniform(-half, half, (n, 3))
        face = rng.integers(0, 3, n)
        p[np.arange(n), face] = half[face] * rng.choice([-1.0, 1.0], n)
        corners = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)]) * half
        return np.vstack([p, corners, rng.uniform(-half, half, (n, 3))])
    v, t = mesh_arrays(geometry)
    return np.vstack([_triangles(v, t, n, rng), v[np.unique(t)]])


def _joint_points(robot, link: str, n: int, seed: int) -> np.ndarray:
    gm = robot.build_geometry("collision")
    rng = np.random.default_rng(seed)
    out = []
    for go in gm.geometryObjects:
        if robot.model.frames[int(go.parentFrame)].name != link:
            continue
        p = surface_points(go.geometry, n, rng)
        out.append(p @ np.asarray(go.placement.rotation).T + np.asarray(go.placement.translation))
    return np.vstack(out)


def _outside(points: np.ndarray, centres: np.ndarray, radii: np.ndarray) -> np.ndarray:
    """Per point: how far it is outside the union of the spheres (<= 0: inside) [m]."""
    d = np.linalg.norm(points[:, None, :] - centres[None, :, :], axis=2) - radii[None, :]
    return d.min(axis=1)


_ROBOTS = ("panda", "ur5_robotiq", "user_mixed")


def _load(name: str, folder) -> object:
    if name == "panda":
        return load_robot("panda")
    if name == "ur5_robotiq":
        return load_robot("ur5", "robotiq_2f_85")
    return load_robot(write_mixed_arm(folder))


@pytest.mark.parametrize("name", _ROBOTS)
def test_every_link_point_inside_its_spheres(name: str, tmp_path) -> None:
    robot = _load(name, tmp_path)
    model = link_spheres(robot)
    counts = sphere_counts(model)
    assert set(counts) == {
        robot.model.frames[int(go.parentFrame)].name
        for go in robot.build_geometry("collision").geometryObjects
    }
    for s in model:
        assert 1 <= counts[s.link] <= 8 * 8  # a few spheres per geometry object
        assert np.all(s.radii > 0)
        pts = _joint_points(robot, s.link, 4000, seed=20261204)
        worst = _outside(pts, s.centres, s.radii)
        assert worst.max() <= 1e-9, (s.link, float(worst.max()))


@pytest.mark.parametrize(
    "geometry",
    [
        coal.Sphere(0.05),
        coal.Capsule(0.03, 0.2),
        coal.Cylinder(0.035, 0.22),
        coal.Box(0.02, 0.1, 0.3),
    ],
    ids=["sphere", "capsule", "cylinder", "box"],
)
def test_primitive_spheres_contain_the_solid(geometry) -> None:
    cover = geometry_spheres(geometry)
    pts = surface_points(geometry, 20000, np.random.default_rng(3))
    assert _outside(pts, cover.centres, cover.radii).max() <= 1e-9


def test_spheres_are_not_loose_for_a_long_cylinder() -> None:
    """The cover hugs the shape: no sphere centre is farther out than the shape's extent."""
    g = coal.Cylinder(0.02, 0.3)  # radius 2 cm, 60 cm long
    cover = geometry_spheres(g)
    assert len(cover.radii) >= 4
    assert cover.radii.max() < 0.1  # one ball around it would need 30 cm
    # a point 3 cm off the axis mid-way, outside the cylinder, is outside the spheres too
    assert _outside(np.array([[0.05, 0.0, 0.0]]), cover.centres, cover.radii)[0] > 0


@pytest.mark.parametrize("name", _ROBOTS)
def test_the_checkers_covers_hold_every_point_of_their_geometry(name: str, tmp_path) -> None:
    """The broad phase's spheres, placed as the checker places them, contain the geometry.

    In five random configurations, every sampled point of each robot geometry
    (placed by Pinocchio) lies inside the union of its cover spheres (placed by
    the checker's joint frames), and every cover sphere inside the geometry's ball:
    the premise of "apart by the spheres, so apart" in levels 1 and 2.
    """
    checker = bottle_checker(name, tmp_path)
    robot, gm, cov = checker.robot, checker._gm, checker._cover
    n_robot = len(cov.start) - 1
    assert n_robot == len(checker.link_names) > 5
    assert {type(gm.geometryObjects[g].geometry) for g in range(n_robot)} >= (
        {coal.BVHModelOBBRSS, coal.Box}
        | ({coal.Cylinder, coal.Sphere} if name == "user_mixed" else set())
    )
    q = robot.random_configurations(5, 21)
    frames = checker._frames.compute(q)
    data, gd = robot.model.createData(), pin.GeometryData(gm)
    rng = np.random.default_rng(20261205)
    local = {g: surface_points(gm.geometryObjects[g].geometry, 1500, rng) for g in range(n_robot)}
    for i, qi in enumerate(q):
        pin.updateGeometryPlacements(robot.model, data, gm, gd, qi)
        for g in range(n_robot):
            m = gd.oMg[g]
            pts = local[g] @ np.asarray(m.rotation).T + np.asarray(m.translation)
            e = slice(cov.start[g], cov.start[g + 1])
            tf = frames.transforms[int(cov.joint[cov.start[g]])][i]
            assert np.all(cov.joint[e] == cov.ball_joint[g])
            centres = cov.centre[e] @ tf[:, :3].T + tf[:, 3]
            worst = _outside(pts, centres, cov.radius[e])
            assert worst.max() <= 1e-9, (name, checker.link_names[g], float(worst.max()))
            ball = tf[:, :3] @ cov.ball_centre[g] + tf[:, 3]
            out = np.linalg.norm(centres - ball, axis=1) + cov.radius[e] - cov.ball_radius[g]
            assert out.max() <= 1e-12, (name, checker.link_names[g], float(out.max()))
