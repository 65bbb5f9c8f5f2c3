r"""The contact-tolerance model: gripper collision pieces eroded by the tolerance.

A grasp touches the object by design, so the gripper may press into it a
little: ``environment.contact_tolerance`` ``t`` [m]. For a **mesh object** the
tolerance is applied on the gripper side. Every convex collision piece ``G`` of
the gripper (a box, sphere, capsule, cylinder or convex mesh of the hand or a
finger) is replaced by its erosion

.. math::

    G \ominus B_t = \{x \in G : \operatorname{dist}(x, \partial G) \ge t\},

which is again convex and is computed exactly: a box, sphere, capsule or
cylinder shrinks by ``t`` on every side; a convex polytope moves each of its
face planes inward by ``t`` (the intersection of the shifted half-spaces). The
eroded piece is checked against the *original* object, as a solid: the gripper
collides with a mesh object exactly when

    some point of the object (its surface or its inside) lies deeper than ``t``
    inside one of the gripper's convex collision pieces (depth = distance to that
    piece's boundary),

i.e. when an eroded piece crosses the object's surface (coal, on the triangles)
or lies inside the closed mesh (:class:`SolidMesh`, one point of the piece).
Two properties follow, whatever the object's shape or wall thickness: (a) a
gripper that does not touch the object is never reported (the eroded piece lies
inside the original one), and (b) an object point deeper than ``t`` inside a
piece is always reported (it lies inside the eroded piece). A piece
thinner than ``2 t`` in some direction erodes to nothing: no point can be deeper
than ``t`` inside it. Erosion of a single convex piece is exact; the erosion of
a union of pieces can be larger than the union of their erosions, so depth is
measured per piece. A gripper mesh that is not convex cannot be eroded this way
(:func:`erode_convex` raises :class:`NotConvexError`); the caller then checks it
as it is (tolerance 0 for that piece), which keeps (a) and (b).

Eroding the object instead (moving a mesh's faces inward) fails on thin walls:
the offsets of a 3 mm mug wall cross each other for a 5 mm tolerance and the
"eroded" surface pokes out of the original one, so a finger pad that does not
touch the mug collides with it. Primitive objects (cylinder, box, sphere,
plane) are convex and keep their exact object-side erosion (see
:func:`gcm_pipeline.robot.collision.shape_geometry`).
"""

from __future__ import annotations

from typing import Any

import coal
import numpy as np
from scipy.optimize import linprog
from scipy.spatial import ConvexHull, HalfspaceIntersection, QhullError

__all__ = ["NotConvexError", "SolidMesh", "erode_convex", "interior_point", "mesh_arrays"]

#: Relative difference of a mesh's volume and its convex hull's below which the
#: mesh counts as convex (meshes exported from CAD hulls differ by ~1e-4).
CONVEX_VOLUME_RTOL = 1e-3


class NotConvexError(ValueError):
    """A collision piece that is not convex (or of a type that cannot be eroded)."""


def mesh_arrays(mesh: Any) -> tuple[np.ndarray, np.ndarray]:
    """Vertices (V, 3) [m] and triangles (T, 3) int of a coal BVH mesh."""
    verts = np.asarray(mesh.vertices(), dtype=float).reshape(-1, 3)
    tris = np.array(
        [[int(t[0]), int(t[1]), int(t[2])] for t in map(mesh.tri_indices, range(mesh.num_tris))],
        dtype=int,
    ).reshape(-1, 3)
    return verts, tris


def _closed_volume(verts: np.ndarray, tris: np.ndarray) -> float:
    a, b, c = verts[tris[:, 0]], verts[tris[:, 1]], verts[tris[:, 2]]
    return float(abs(np.einsum("ij,ij->i", a, np.cross(b, c)).sum()) / 6.0)


def _convex_from_points(points: np.ndarray) -> Any:
    vec = coal.StdVec_Vec3s()
    for p in np.asarray(points, dtype=float):
        vec.append(p)
    return coal.Convex.convexHull(vec, True, "Qt")


def _erode_polytope(points: np.ndarray, distance: float) -> Any | None:
    """Erosion of the convex hull of ``points`` by ``distance``: its faces moved inward."""
    try:
        hull = ConvexHull(points)
    except QhullError as exc:
        raise NotConvexError(f"degenerate convex piece (flat or too few points): {exc}") from exc
    eq = hull.equations.copy()  # n . x + b <= 0 inside, |n| = 1
    eq[:, 3] += distance
    # Chebyshev centre of the shifted half-spaces: max r s.t. n . x + b + r <= 0
    a_ub = np.hstack([eq[:, :3], np.ones((len(eq), 1))])
    res = linprog(
        c=[0, 0, 0, -1], A_ub=a_ub, b_ub=-eq[:, 3], bounds=[(None, None)] * 3 + [(0, None)]
    )
    if not res.success or res.x[3] <= 1e-9:
        return None  # the piece is thinner than 2 * distance everywhere: nothing remains
    centre = res.x[:3]
    try:
        verts = HalfspaceIntersection(eq, centre).intersections
    except QhullError:  # pragma: no cover - a remaining sliver too thin for Qhull
        return None
    verts = verts[np.all(np.isfinite(verts), axis=1)]
    try:
        ConvexHull(verts)
    except QhullError:
        return None  # flat remainder: no volume left
    return _convex_from_points(verts)


def erode_convex(geometry: Any, distance: float) -> Any | None:
    """Erosion of a convex coal collision piece by ``distance`` [m] (exact).

    Args:
        geometry: A ``coal.Box``, ``coal.Sphere``, ``coal.Capsule``,
            ``coal.Cylinder``, ``coal.Convex`` or a BVH mesh that is convex
            (its volume equals its convex hull's within
            :data:`CONVEX_VOLUME_RTOL`), in its own frame.
        distance: Erosion distance ``t`` >= 0 [m].

    Returns:
        A new coal geometry in the same frame holding exactly the points of the
        piece at distance >= ``t`` from its boundary (a ``coal.Convex`` for
        polytopes, the same primitive type otherwise); None when nothing
        remains (the piece is nowhere thicker than ``2 t``). ``distance == 0``
        returns ``geometry`` itself.

    Raises:
        NotConvexError: A mesh that is not convex, a degenerate mesh, or a
            geometry type that cannot be eroded (a plane, a height field).
        ValueError: Negative or non-finite ``distance``.
    """
    d = float(distance)
    if not np.isfinite(d) or d < 0:
        raise ValueError(f"erosion distance must be >= 0 [m], got {distance!r}")
    if d == 0:
        return geometry
    if isinstance(geometry, coal.Box):
        half = np.asarray(geometry.halfSide, dtype=float) - d
        return coal.Box(*(2 * half)) if np.all(half > 0) else None
    if isinstance(geometry, coal.Sphere):
        r = float(geometry.radius) - d
        return coal.Sphere(r) if r > 0 else None
    if isinstance(geometry, coal.Capsule):  # a segment swept by a sphere: radius shrinks
        r = float(geometry.radius) - d
        return coal.Capsule(r, 2 * float(geometry.halfLength)) if r > 0 else None
    if isinstance(geometry, coal.Cylinder):
        r, h = float(geometry.radius) - d, float(geometry.halfLength) - d
        return coal.Cylinder(r, 2 * h) if r > 0 and h > 0 else None
    if isinstance(geometry, coal.ConvexBase):
        pts = np.array(geometry.points(), dtype=float).reshape(-1, 3)
        return _erode_polytope(pts, d)
    if isinstance(geometry, coal.BVHModelBase):
        verts, tris = mesh_arrays(geometry)
        try:
            hull_volume = ConvexHull(verts).volume
        except QhullError as exc:
            raise NotConvexError(f"degenerate mesh (flat or too few vertices): {exc}") from exc
        volume = _closed_volume(verts, tris)
        if abs(hull_volume - volume) > CONVEX_VOLUME_RTOL * hull_volume:
            raise NotConvexError(
                f"mesh is not convex (volume {volume:.3g} m^3, convex hull {hull_volume:.3g} m^3)"
            )
        return _erode_polytope(verts, d)
    raise NotConvexError(f"cannot erode a {type(geometry).__name__}")


def interior_point(geometry: Any) -> np.ndarray:
    """A point of a coal collision piece, in its own frame (3,) [m].

    The centre of a primitive, the mean of a convex polytope's vertices, the
    first vertex of a mesh (a point of its surface, so of the piece). A piece
    that crosses no surface of a closed mesh lies wholly inside or wholly
    outside it, so this one point decides which (see :class:`SolidMesh`).
    """
    if isinstance(geometry, coal.ConvexBase):
        pts = np.array(geometry.points(), dtype=float).reshape(-1, 3)
        return pts.mean(axis=0)
    if isinstance(geometry, coal.BVHModelBase):
        return np.asarray(geometry.vertices(), dtype=float).reshape(-1, 3)[0].copy()
    return np.zeros(3)


class SolidMesh:
    """Inside test of a closed triangle mesh: signed crossings of a ray.

    A point is inside when the triangles crossed by a ray from it, counted
    +1 or -1 by the side they face, do not sum to zero (the winding number
    along the ray; 1 inside a closed, consistently oriented mesh, 2 where two
    closed parts overlap). The ray leaves along a fixed direction that is not
    aligned with any axis, so axis-aligned meshes do not put points on its
    edges; a ray through a triangle edge or vertex (a set of measure zero) may
    miscount. Triangles are binned on a grid across the ray so each point
    tests only the triangles of its cell. Meshes that are not closed have no
    inside; the count is then not meaningful.

    Args:
        vertices: (V, 3) [m].
        triangles: (T, 3) vertex indices.
        cells: Grid cells along each axis across the ray.
    """

    _DIRECTION = np.array([0.2718281828, 0.1414213562, 1.0])

    def __init__(self, vertices: np.ndarray, triangles: np.ndarray, cells: int = 64) -> None:
        d = self._DIRECTION / np.linalg.norm(self._DIRECTION)
        ex = np.cross(d, [1.0, 0.0, 0.0])
        ex /= np.linalg.norm(ex)
        self._rot = np.stack([ex, np.cross(d, ex), d])  # rows: x', y', ray
        v = np.asarray(vertices, dtype=float) @ self._rot.T
        tri = v[np.asarray(triangles, dtype=int)]  # (T, 3, 3) in the ray frame
        a, b, c = tri[:, 0, :2], tri[:, 1, :2], tri[:, 2, :2]
        area = (b[:, 0] - a[:, 0]) * (c[:, 1] - a[:, 1]) - (b[:, 1] - a[:, 1]) * (c[:, 0] - a[:, 0])
        keep = np.abs(area) > 1e-300  # triangles seen edge-on are never crossed
        self._tri = tri[keep]
        self._sign = np.sign(area[keep])
        self._area = area[keep]
        self.bounds = np.array([v.min(axis=0), v.max(axis=0)]) if len(v) else np.zeros((2, 3))
        self.local_bounds = (
            np.array([vertices.min(axis=0), vertices.max(axis=0)]) if len(v) else np.zeros((2, 3))
        )
        lo, hi = self.bounds[0, :2], self.bounds[1, :2]
        self._lo = lo
        self._cell = np.maximum((hi - lo) / cells, 1e-12)
        self._n = cells
        tlo = np.clip(
            ((self._tri[:, :, :2].min(axis=1) - lo) / self._cell).astype(int), 0, cells - 1
        )
        thi = np.clip(
            ((self._tri[:, :, :2].max(axis=1) - lo) / self._cell).astype(int), 0, cells - 1
        )
        span = thi - tlo + 1
        count = span[:, 0] * span[:, 1]
        tid = np.repeat(np.arange(len(self._tri)), count)
        k = np.arange(count.sum()) - np.repeat(np.cumsum(count) - count, count)
        sx = np.repeat(span[:, 0], count)
        cx = np.repeat(tlo[:, 0], count) + k % sx
        cy = np.repeat(tlo[:, 1], count) + k // sx
        cell = cx * cells + cy
        order = np.argsort(cell, kind="stable")
        self._cell_tris = tid[order]
        self._cell_start = np.searchsorted(cell[order], np.arange(cells * cells + 1))

    def contains(self, points: np.ndarray, chunk: int = 1_000_000) -> np.ndarray:
        """Whether each point (N, 3) [m, mesh frame] is inside the mesh, (N,) bool."""
        p = np.asarray(points, dtype=float).reshape(-1, 3) @ self._rot.T
        out = np.zeros(len(p), dtype=bool)
        inb = np.all((p[:, :2] >= self._lo) & (p[:, :2] <= self.bounds[1, :2]), axis=1)
        inb &= p[:, 2] <= self.bounds[1, 2]
        rows = np.flatnonzero(inb)
        if rows.size == 0 or len(self._tri) == 0:
            return out
        ij = np.clip(((p[rows, :2] - self._lo) / self._cell).astype(int), 0, self._n - 1)
        cell = ij[:, 0] * self._n + ij[:, 1]
        start, stop = self._cell_start[cell], self._cell_start[cell + 1]
        count = stop - start
        winding = np.zeros(rows.size)
        ends = np.cumsum(count)  # (point, triangle) pairs, in chunks of about `chunk`
        first = 0
        while first < rows.size:
            done = int(ends[first - 1]) if first else 0
            last = max(int(np.searchsorted(ends, done + chunk, "right")), first + 1)
            n = count[first:last]
            pi = np.repeat(np.arange(first, last), n)
            k = np.arange(n.sum()) - np.repeat(np.cumsum(n) - n, n)
            ti = self._cell_tris[np.repeat(start[first:last], n) + k]
            winding[first:last] = np.bincount(
                pi - first, weights=self._crossings(p[rows[pi]], ti), minlength=last - first
            )
            first = last
        out[rows] = np.abs(winding) > 0.5
        return out

    def _crossings(self, p: np.ndarray, ti: np.ndarray) -> np.ndarray:
        """Signed crossing (+1, -1 or 0) of the ray from each point with each triangle."""
        tri = self._tri[ti]
        a, b, c = tri[:, 0], tri[:, 1], tri[:, 2]
        x, y = p[:, 0], p[:, 1]
        w0 = (b[:, 0] - x) * (c[:, 1] - y) - (b[:, 1] - y) * (c[:, 0] - x)
        w1 = (c[:, 0] - x) * (a[:, 1] - y) - (c[:, 1] - y) * (a[:, 0] - x)
        w2 = (a[:, 0] - x) * (b[:, 1] - y) - (a[:, 1] - y) * (b[:, 0] - x)
        s = self._sign[ti]
        inside = (w0 * s > 0) & (w1 * s > 0) & (w2 * s > 0)
        area = self._area[ti]
        z = (w0 * a[:, 2] + w1 * b[:, 2] + w2 * c[:, 2]) / area
        return np.where(inside & (z > p[:, 2]), s, 0.0)
