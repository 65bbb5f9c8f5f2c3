"""Sphere covers and hull vertices of collision geometries (the broad phase's bounds).

Every robot collision geometry is covered by a few spheres (:func:`sphere_cover`:
the geometry cut into slabs along its long axis, each slab's part inside one
sphere, so the union of the spheres contains the geometry) and by one sphere
around those (:func:`robot_covers`), in its joint's rotated frame; its convex
hull's vertices (:func:`hull_vertices`) decide polytope-box pairs.
"""

from __future__ import annotations

from typing import Any, NamedTuple

import coal
import numpy as np
from scipy.spatial import ConvexHull, QhullError

from gcm_pipeline.robot.chain import JointFrames
from gcm_pipeline.robot.collision.contact import mesh_arrays

__all__ = [
    "POLYTOPES",
    "RobotCover",
    "SphereCover",
    "geometry_mesh",
    "hull_vertices",
    "polytope_edges",
    "robot_covers",
    "sphere_cover",
]

#: Geometries whose points are the convex combinations of their vertices' (hull).
POLYTOPES = (coal.BVHModelBase, coal.ConvexBase, coal.Box)


class SphereCover(NamedTuple):
    """Spheres whose union contains a geometry (in the frame the points were given in).

    Attributes:
        centres: (K, 3) [m].
        radii: (K,) [m].
    """

    centres: np.ndarray
    radii: np.ndarray


def _box_mesh(lo: np.ndarray, hi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Corners (8, 3) and triangles (12, 3) of an axis-aligned box."""
    corners = np.array(
        [[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])]
    )
    faces = [(0, 1, 3, 2), (4, 6, 7, 5), (0, 4, 5, 1), (2, 3, 7, 6), (0, 2, 6, 4), (1, 5, 7, 3)]
    tris = [(a, b, c) for a, b, c, d in faces] + [(a, c, d) for a, b, c, d in faces]
    return corners, np.array(tris, dtype=int)


def geometry_mesh(geometry: Any) -> tuple[np.ndarray, np.ndarray]:
    """Points (V, 3) and triangles (T, 3) whose triangles cover a coal geometry.

    A mesh gives its own triangles (coal checks a mesh as its surface); a
    convex polytope its hull's; a box its faces; any other shape (sphere,
    cylinder, capsule, ...) the faces of its local bounding box, which contains it.
    """
    if isinstance(geometry, coal.BVHModelBase):
        return mesh_arrays(geometry)
    if isinstance(geometry, coal.ConvexBase):
        pts = np.array(geometry.points(), dtype=float).reshape(-1, 3)
        try:
            return pts, ConvexHull(pts).simplices.astype(int)
        except (QhullError, ValueError):
            pass
    geometry.computeLocalAABB()
    box = geometry.aabb_local
    return _box_mesh(np.asarray(box.min_, dtype=float), np.asarray(box.max_, dtype=float))


def sphere_cover(points: np.ndarray, triangles: np.ndarray, max_spheres: int = 8) -> SphereCover:
    """Spheres whose union contains every triangle (and so their convex hull's parts).

    The geometry is cut into ``K`` slabs of equal length along its principal
    axis (``K`` about twice its length over its width, at most
    ``max_spheres``). The part of the triangles inside a slab lies in the convex
    hull of the vertices in the slab and of the points where triangle edges
    cross the slab's planes; one sphere per slab contains all those points,
    hence that part. The cover of a solid convex piece given by its hull's
    triangles contains the solid too.

    Args:
        points: Vertices (V, 3) [m].
        triangles: (T, 3) int.
        max_spheres: Upper bound of ``K``.

    Returns:
        The :class:`SphereCover`.
    """
    v = np.asarray(points, dtype=float).reshape(-1, 3)
    tris = np.asarray(triangles, dtype=int).reshape(-1, 3)
    mean = v.mean(axis=0)
    _, _, vt = np.linalg.svd(v - mean, full_matrices=False)
    axis = vt[0]
    t = (v - mean) @ axis
    lo, hi = float(t.min()), float(t.max())
    radial = np.linalg.norm((v - mean) - np.outer(t, axis), axis=1).max()
    length = hi - lo
    k = int(np.clip(np.ceil(2.0 * length / max(2.0 * radial, 1e-6)), 1, max_spheres))
    planes = lo + length * np.arange(1, k) / k
    edges = np.unique(
        np.sort(np.concatenate([tris[:, [0, 1]], tris[:, [1, 2]], tris[:, [2, 0]]]), axis=1), axis=0
    )
    ta, tb = t[edges[:, 0]], t[edges[:, 1]]
    extra_pts, extra_t = [], []
    for plane in planes:
        cross = (np.minimum(ta, tb) < plane) & (np.maximum(ta, tb) > plane)
        if np.any(cross):
            e = edges[cross]
            f = ((plane - t[e[:, 0]]) / (t[e[:, 1]] - t[e[:, 0]]))[:, None]
            extra_pts.append(v[e[:, 0]] + f * (v[e[:, 1]] - v[e[:, 0]]))
            extra_t.append(np.full(int(cross.sum()), plane))
    pts = np.concatenate([v, *extra_pts]) if extra_pts else v
    pt_t = np.concatenate([t, *extra_t]) if extra_t else t
    bounds = lo + length * np.arange(k + 1) / k
    centres, radii = [], []
    eps = 1e-12 * max(1.0, length)
    for i in range(k):
        sel = (pt_t >= bounds[i] - eps) & (pt_t <= bounds[i + 1] + eps)
        if not np.any(sel):
            continue
        p = pts[sel]
        c = 0.5 * (p.min(axis=0) + p.max(axis=0))
        centres.append(c)
        radii.append(float(np.linalg.norm(p - c, axis=1).max()) * (1.0 + 1e-9) + 1e-12)
    return SphereCover(np.array(centres), np.array(radii))


class RobotCover(NamedTuple):
    """Sphere covers of all robot geometries, in the joints' rotated frames."""

    centre: np.ndarray  # (S, 3)
    radius: np.ndarray  # (S,)
    joint: np.ndarray  # (S,)
    start: np.ndarray  # (R + 1,) spheres of geometry g: start[g]:start[g + 1]
    ball_centre: np.ndarray  # (R, 3) one sphere per geometry containing its cover
    ball_radius: np.ndarray  # (R,)
    ball_joint: np.ndarray  # (R,)


def robot_covers(gm: Any, ids: list[int], frames: JointFrames, max_spheres: int) -> RobotCover:
    """Sphere covers of robot geometries ``ids`` of ``gm`` in their joints' rotated frames."""
    centres, radii, joints, start = [], [], [], [0]
    balls: list[np.ndarray] = []
    ball_r: list[float] = []
    for i in ids:
        go = gm.geometryObjects[i]
        pts, tris = geometry_mesh(go.geometry)
        cov = sphere_cover(pts, tris, max_spheres)
        j = int(go.parentJoint)
        rot, trans = frames.local(
            j, np.asarray(go.placement.rotation), np.asarray(go.placement.translation)
        )
        centres.append(cov.centres @ rot.T + trans)
        radii.append(cov.radii)
        joints.append(np.full(len(cov.radii), j))
        start.append(start[-1] + len(cov.radii))
        # the sphere around the cover's spheres: centred in their bounding box
        c = centres[-1]
        mid = 0.5 * (c.min(axis=0) + c.max(axis=0))
        balls.append(mid)
        ball_r.append(float((np.linalg.norm(c - mid, axis=1) + cov.radii).max()) * (1 + 1e-12))
    return RobotCover(
        np.concatenate(centres),
        np.concatenate(radii),
        np.concatenate(joints),
        np.array(start),
        np.array(balls).reshape(-1, 3),
        np.array(ball_r),
        np.array([int(gm.geometryObjects[i].parentJoint) for i in ids], dtype=int),
    )


def hull_vertices(go: Any, frames: JointFrames) -> tuple[int, np.ndarray]:
    """A robot geometry's convex hull vertices in its joint's rotated frame: ``(joint, (V, 3))``.

    Only vertices of its triangles count (a mesh may list unused ones): each
    hull vertex is a point of the geometry.
    """
    pts, tris = geometry_mesh(go.geometry)
    pts = pts[np.unique(tris)] if tris.size else pts
    try:
        pts = pts[ConvexHull(pts).vertices]
    except (QhullError, ValueError):
        pass
    j = int(go.parentJoint)
    rot, trans = frames.local(
        j, np.asarray(go.placement.rotation), np.asarray(go.placement.translation)
    )
    return j, pts @ rot.T + trans


def polytope_edges(go: Any, frames: JointFrames, count: int) -> tuple[int, np.ndarray, np.ndarray]:
    """The ``count`` longest edges of a robot polytope's triangles, longest first.

    ``(joint, ends (E, 3), other ends (E, 3))`` in its joint's rotated frame.
    Every edge lies on the geometry as coal checks it (a mesh's surface, a convex
    piece's or a box's solid), so a point of an edge inside a world shape is a
    contact with it.
    """
    pts, tris = geometry_mesh(go.geometry)
    edges = np.sort(np.concatenate([tris[:, [0, 1]], tris[:, [1, 2]], tris[:, [0, 2]]]), axis=1)
    edges = np.unique(edges, axis=0) if edges.size else edges.reshape(0, 2)
    length = np.linalg.norm(pts[edges[:, 0]] - pts[edges[:, 1]], axis=1)
    edges = edges[np.argsort(-length, kind="stable")[:count]]
    j = int(go.parentJoint)
    rot, trans = frames.local(
        j, np.asarray(go.placement.rotation), np.asarray(go.placement.translation)
    )
    return j, pts[edges[:, 0]] @ rot.T + trans, pts[edges[:, 1]] @ rot.T + trans
