"""Outer sphere models of a robot's links, generated from their collision geometry.

For each link that carries collision geometry, a few spheres in the frame of
the link's parent joint whose union contains every collision geometry of the
link (conservative: a configuration whose spheres touch nothing is free by
exact geometry too). This is the model VAMP's checker hand-writes per robot
(its Panda has 59 spheres); here it is generated for any URDF and tool:

* a sphere is its own model (one sphere, exact);
* a capsule (a segment of half-length ``h``, radius ``r``): ``k`` spheres
  centred on the segment at spacing ``s = 2h / k``, radius ``r + s / 2``
  (every point of the capsule is within ``r`` of a point of the segment, and
  that point within ``s / 2`` of a centre);
* a cylinder: the prism over the circumscribed ``n``-gon (it contains the
  cylinder), covered as a convex polytope;
* a box, a convex polytope or a mesh: :func:`~gcm_pipeline.robot.collision.spheres.sphere_cover`
  of its triangles (the geometry cut into slabs along its principal axis, one
  sphere per slab through every vertex and edge crossing of the slab), which
  contains every triangle, and the solid too for a convex piece.

Not wired into the checker yet: :func:`link_spheres`
builds the model, :func:`sphere_counts` reports its size.
"""

from __future__ import annotations

from typing import Any, NamedTuple

import coal
import numpy as np

from gcm_pipeline.robot.collision.spheres import SphereCover, geometry_mesh, sphere_cover

__all__ = ["LinkSpheres", "geometry_spheres", "link_spheres", "sphere_counts"]

#: Sides of the polygon circumscribed about a cylinder's circular section.
CYLINDER_SIDES = 16


class LinkSpheres(NamedTuple):
    """The outer spheres of one link, in its parent joint's frame.

    Attributes:
        link: The link's frame name.
        joint: Index of its parent joint in the model.
        centres: (K, 3) [m].
        radii: (K,) [m].
    """

    link: str
    joint: int
    centres: np.ndarray
    radii: np.ndarray


def _prism(radius: float, half_length: float, sides: int) -> tuple[np.ndarray, np.ndarray]:
    """Vertices and triangles of the prism over the ``sides``-gon circumscribed about a circle."""
    ang = 2.0 * np.pi * (np.arange(sides) + 0.5) / sides
    rc = radius / np.cos(np.pi / sides)  # the polygon's vertices: its edges touch the circle
    ring = np.column_stack([rc * np.cos(ang), rc * np.sin(ang)])
    pts = np.vstack(
        [np.column_stack([ring, np.full(sides, z)]) for z in (-half_length, half_length)]
        + [[[0.0, 0.0, -half_length], [0.0, 0.0, half_length]]]
    )
    i = np.arange(sides)
    j = (i + 1) % sides
    lo, hi = 2 * sides, 2 * sides + 1
    tris = np.vstack(
        [
            np.column_stack([i, j, sides + i]),
            np.column_stack([j, sides + j, sides + i]),
            np.column_stack([np.full(sides, lo), j, i]),
            np.column_stack([np.full(sides, hi), sides + i, sides + j]),
        ]
    )
    return pts, tris


def geometry_spheres(geometry: Any, max_spheres: int = 8) -> SphereCover:
    """Spheres whose union contains a coal geometry, in the geometry's own frame.

    Args:
        geometry: A coal collision geometry (sphere, capsule, cylinder, box,
            convex polytope or mesh; any other shape is covered through its
            local bounding box).
        max_spheres: Upper bound of the spheres of one geometry.

    Returns:
        The :class:`~gcm_pipeline.robot.collision.spheres.SphereCover`.
    """
    if isinstance(geometry, coal.Sphere):
        return SphereCover(np.zeros((1, 3)), np.array([float(geometry.radius)]))
    if isinstance(geometry, coal.Capsule):
        r, h = float(geometry.radius), float(geometry.halfLength)
        k = int(np.clip(np.ceil(h / max(r, 1e-9)), 1, max_spheres))
        s = 2.0 * h / k
        z = -h + s * (np.arange(k) + 0.5)
        centres = np.column_stack([np.zeros(k), np.zeros(k), z])
        return SphereCover(centres, np.full(k, (r + 0.5 * s) * (1.0 + 1e-9)))
    if isinstance(geometry, coal.Cylinder):
        pts, tris = _prism(float(geometry.radius), float(geometry.halfLength), CYLINDER_SIDES)
        return sphere_cover(pts, tris, max_spheres)
    pts, tris = geometry_mesh(geometry)
    return sphere_cover(pts, tris, max_spheres)


def link_spheres(robot: Any, max_spheres: int = 8) -> list[LinkSpheres]:
    """The outer spheres of every link with collision geometry, in model order.

    Args:
        robot: A :class:`~gcm_pipeline.robot.model.Robot` (its collision
            geometry, tool included).
        max_spheres: Upper bound of the spheres of one geometry object.

    Returns:
        One :class:`LinkSpheres` per link, spheres in the parent joint's frame.
    """
    gm = robot.build_geometry("collision")
    model = robot.model
    links: dict[str, list[np.ndarray]] = {}
    radii: dict[str, list[np.ndarray]] = {}
    joints: dict[str, int] = {}
    for go in gm.geometryObjects:
        cover = geometry_spheres(go.geometry, max_spheres)
        rot = np.asarray(go.placement.rotation)
        trans = np.asarray(go.placement.translation)
        link = str(model.frames[int(go.parentFrame)].name)
        links.setdefault(link, []).append(cover.centres @ rot.T + trans)
        radii.setdefault(link, []).append(cover.radii)
        joints[link] = int(go.parentJoint)
    return [
        LinkSpheres(link, joints[link], np.concatenate(links[link]), np.concatenate(radii[link]))
        for link in links
    ]


def sphere_counts(model: list[LinkSpheres]) -> dict[str, int]:
    """Spheres per link of a model (link name -> count)."""
    return {s.link: len(s.radii) for s in model}
