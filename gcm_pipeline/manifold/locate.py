r"""Nearest points of the grasp manifold: :class:`TriangleLocator`, :func:`as_query_poses`.

:class:`TriangleLocator` answers "which point of the manifold is nearest to
this pose" for batches of queries, exactly up to the projection's tolerance
(a projection is a local minimum: far from the manifold, a metre or more, a
triangle can hold several and the point found may be a little farther than
the nearest; :mod:`gcm_pipeline.manifold.surface`).
The manifold is its triangles plus its isolated points: candidates that no
kept triangle uses are points of the manifold too (a query at one's exact
pose finds it at distance 0).

0. the nearest isolated point of each query comes from a KD-tree over their
   features (both quaternion signs; the metric is Euclidean there, so this
   is exact);
1. every triangle gets a bounding slab in the 7-D features (centre, best-fit
   plane, in-plane extent, thickness, measured on a lattice of its points and
   enlarged for the curvature between them), so the distance from a query to
   any point of the triangle has a cheap lower bound;
2. the distance to beat starts at a point of the manifold: the nearer of the
   nearest isolated point and the nearest point of a coarse lattice on the
   triangle of the query's nearest centre;
3. triangles whose centre lies within that distance plus their size (ball
   queries in KD-trees over the centres, both quaternion signs) are bounded;
   per query, in the order of their bounds, the lowest is projected first,
   then every other whose bound is still below the distance found. A pruned
   triangle's bound is at or above a distance already reached, so it holds
   no nearer point: the answer equals projecting onto every triangle
   (``TriangleLocator.locate(..., exhaustive=True)``) and taking the nearer
   of that and the nearest isolated point. (An isolated point lowers the
   distance to beat; it is a point of the manifold, so every pruning
   argument still holds.)
"""

from __future__ import annotations

import itertools
from typing import Any, NamedTuple

import numpy as np
import numpy.typing as npt
from scipy.spatial import cKDTree

from gcm_pipeline.bounds import MAX_LENGTH
from gcm_pipeline.errors import GeometryError, choice_error
from gcm_pipeline.geometry.dualquat import dq_from_matrix, dq_translation
from gcm_pipeline.geometry.pose_metric import ORIENTATION_SCALE, pose_distance, pose_features
from gcm_pipeline.manifold.surface import BLEND_METHODS, blend, project_onto_triangles

__all__ = ["Location", "TriangleLocator", "as_query_poses"]

_UNIT_TOL = 1e-6  # |real| - 1 and real.dual of a query dual quaternion

_FLIP = np.array([1.0, 1.0, 1.0, -1.0, -1.0, -1.0, -1.0])  # the other quaternion sign


class Location(NamedTuple):
    """Nearest manifold points of M query poses.

    Attributes:
        triangle: (M,) int index of the triangle holding the nearest point;
            -1 where it is an isolated point (see ``vertex``).
        weights: (M, 3) barycentric weights of that point in its triangle;
            ``(1, 0, 0)`` at an isolated point.
        distance: (M,) pose-metric distance [m] from the query to it.
        dq: (M, 8) the nearest point itself (unit dual quaternion, world).
        vertex: (M,) int id of the isolated point that is nearest (for a
            grasp manifold: its candidate row); -1 where a triangle holds it.
    """

    triangle: np.ndarray
    weights: np.ndarray
    distance: np.ndarray
    dq: np.ndarray
    vertex: np.ndarray


# --------------------------------------------------------------------------- query poses
def _check_positions(xyz: np.ndarray, name: str) -> None:
    """Positions within the scene's bounds (``MAX_LENGTH`` per coordinate, as the config's)."""
    bad = (np.abs(xyz) > MAX_LENGTH).any(axis=1)
    if bad.any():
        i = int(np.argmax(bad))
        raise GeometryError(
            f"{name} {i}: position [{', '.join(f'{v:.10g}' for v in xyz[i])}] m is outside the "
            f"scene (at most {MAX_LENGTH:g} m per coordinate)"
        )


def as_query_poses(poses: Any, name: str = "query pose") -> np.ndarray:
    """Validate query poses and return them as unit dual quaternions (M, 8).

    Args:
        poses: (M, 4, 4) or (4, 4) rigid transforms, or (M, 8) or (8,) unit
            dual quaternions ``[r_w, r_x, r_y, r_z, d_w, d_x, d_y, d_z]``.
        name: How to call them in messages.

    Raises:
        GeometryError: Another shape, non-finite values, a matrix that is not
            rigid or a dual quaternion that is not unit (names the first bad one).
    """
    try:
        arr = np.asarray(poses, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise GeometryError(f"{name}s must be numbers: {exc}") from None
    if arr.shape[-2:] == (4, 4) and arr.ndim in (2, 3):
        mats = arr.reshape(-1, 4, 4)
        xyz = mats[:, :3, 3]
        _check_positions(np.where(np.isfinite(xyz), xyz, 0.0), name)  # non-finite: said below
        try:
            return dq_from_matrix(mats)
        except GeometryError as exc:
            raise GeometryError(f"{name}: {exc}") from None
    if arr.ndim in (1, 2) and arr.shape[-1] == 8:
        dq = arr.reshape(-1, 8)
        bad = ~np.isfinite(dq).all(axis=1)
        if bad.any():
            i = int(np.argmax(bad))
            raise GeometryError(f"{name} {i} has non-finite values: {dq[i].tolist()}")
        norm = np.linalg.norm(dq[:, :4], axis=1)
        dot = np.einsum("ij,ij->i", dq[:, :4], dq[:, 4:])
        bad = (np.abs(norm - 1.0) > _UNIT_TOL) | (np.abs(dot) > _UNIT_TOL)
        if bad.any():
            i = int(np.argmax(bad))
            raise GeometryError(
                f"{name} {i} is not a unit dual quaternion (|real| = {norm[i]:.6g}, "
                f"real.dual = {dot[i]:.2e}); pass (4, 4) matrices or dq_from_pos_quat(...)"
            )
        _check_positions(dq_translation(dq), name)
        return dq.copy()
    raise GeometryError(
        f"{name}s must be (M, 4, 4) / (4, 4) matrices or (M, 8) / (8,) dual quaternions, "
        f"got shape {arr.shape}"
    )


# --------------------------------------------------------------------------- locator
def _cells(s: int) -> tuple[np.ndarray, np.ndarray]:
    """The ``s * s`` cells of an ``s``-subdivided triangle.

    Returns:
        ``(centroids (C, 3), corners (C, 3, 3))``: barycentric weights of each
        cell's centroid and of its three corners.
    """
    up, down = [], []
    for i in range(s):
        for j in range(s - i):
            up.append(((i, j), (i + 1, j), (i, j + 1)))
            if i + j < s - 1:
                down.append(((i + 1, j), (i + 1, j + 1), (i, j + 1)))
    ij = np.array(up + down, dtype=np.float64)  # (C, 3, 2): (u, v) * s of the corners
    uv = ij / s
    corners = np.concatenate((1.0 - uv.sum(axis=2, keepdims=True), uv), axis=2)
    return corners.mean(axis=1), corners


def _dedupe(rows: np.ndarray, tris: np.ndarray, t: int) -> tuple[np.ndarray, np.ndarray]:
    """Distinct (row, triangle) pairs, sorted."""
    key = np.sort(rows * t + tris)
    key = key[np.r_[True, key[1:] != key[:-1]]] if key.size else key
    return key // t, key % t


def _point_triangle_2d(p: np.ndarray, tri: np.ndarray) -> np.ndarray:
    """Distance (P,) from 2-D points (P, 2) to filled triangles (P, 3, 2); 0 inside."""
    a, b, c = tri[:, 0], tri[:, 1], tri[:, 2]
    e0, e1 = b - a, c - a
    det = e0[:, 0] * e1[:, 1] - e0[:, 1] * e1[:, 0]
    f = p - a
    safe = np.where(np.abs(det) > 1e-300, det, 1e-300)
    u = (f[:, 0] * e1[:, 1] - f[:, 1] * e1[:, 0]) / safe
    v = (e0[:, 0] * f[:, 1] - e0[:, 1] * f[:, 0]) / safe
    inside = (u >= 0) & (v >= 0) & (u + v <= 1) & (np.abs(det) > 1e-300)
    best = np.full(len(p), np.inf)
    for s0, s1 in ((a, b), (b, c), (c, a)):
        e = s1 - s0
        ee = np.maximum(np.einsum("pi,pi->p", e, e), 1e-300)
        t = np.clip(np.einsum("pi,pi->p", p - s0, e) / ee, 0.0, 1.0)
        d = p - s0 - t[:, None] * e
        best = np.minimum(best, np.sqrt(np.einsum("pi,pi->p", d, d)))
    return np.where(inside, 0.0, best)


def _lattice(s: int) -> np.ndarray:
    """Barycentric weights (P, 3) of the points of an ``s``-subdivided triangle."""
    i, j = np.meshgrid(np.arange(s + 1), np.arange(s + 1), indexing="ij")
    keep = i + j <= s
    return np.stack((s - i[keep] - j[keep], i[keep], j[keep]), axis=1) / float(s)


class TriangleLocator:
    r"""Batched nearest-point queries on a set of blended triangles.

    Every triangle is bounded by a slab in the 7-D feature space of the pose
    metric: its centre ``c``, the best-fit plane of its points (two
    orthonormal directions), the radius ``R`` of its points within that
    plane and their largest distance ``tau`` from it (from a lattice of
    points, enlarged by :attr:`SAFETY` for the blend's curvature between
    them). For a query ``x`` with in-plane offset ``a`` and normal offset
    ``b`` from ``c``, every point of the triangle is at least

    .. math:: \sqrt{\max(0, |a| - R)^2 + \max(0, |b| - \tau)^2}

    away (with the quaternion sign nearer to the centre; the other sign is
    bounded by its distance to the centre minus the triangle's extent). The
    first distance to beat is that of the nearest point of a coarse lattice
    on the triangle of the nearest centre. Candidates are the triangles whose
    centre is within that distance plus the largest extent of their size
    group (ball queries in KD-trees over the centres, both quaternion signs;
    one tree per size group, so a few large triangles do not widen the balls
    of the many small ones). A query is projected onto its lowest-bound
    candidate first (started at its in-plane foot point), then onto every
    other whose bound is below the distance found.

    Isolated points (``points``) are part of the manifold too: the nearest
    of them (a KD-tree over their features, exact) is a candidate answer
    and, when nearer than the lattice point, the first distance to beat.

    Args:
        corners: (T, 3, 8) vertex poses of the T triangles (world); T may be
            0 when there are points.
        points: (P, 8) poses of the isolated points (world), or None.
        point_ids: (P,) int ids reported for them in :attr:`Location.vertex`
            (default ``0 .. P - 1``).
        method: The blend, ``dlb`` or ``dib``.
        orientation_scale: ``L`` [m/rad] of the pose metric.
        subdivisions: Lattice subdivisions of the bounding points.

    Raises:
        GeometryError: Neither a triangle nor a point, wrong shapes, unknown method.
    """

    #: Factor on the bounds measured on the lattice, covering the blend between its points.
    SAFETY = 1.25
    #: Ratio of the largest to the smallest extent within one size group.
    GROUP = 1.5
    #: Subdivisions of the lattice whose nearest point gives the first distance to beat.
    UPPER_SUBDIVISIONS = 3
    #: Rounds projecting each query's lowest-bound triangle before the rest.
    HEAD_PASSES = 1
    #: Leaf size of the KD-trees over the centres.
    LEAF = 64

    def __init__(
        self,
        corners: npt.ArrayLike,
        *,
        points: npt.ArrayLike | None = None,
        point_ids: npt.ArrayLike | None = None,
        method: str = "dlb",
        orientation_scale: float = ORIENTATION_SCALE,
        subdivisions: int = 6,
    ) -> None:
        corners = np.asarray(corners, dtype=np.float64)
        if corners.ndim != 3 or corners.shape[1:] != (3, 8):
            raise GeometryError(f"triangle corners must have shape (T, 3, 8), got {corners.shape}")
        pts = np.zeros((0, 8)) if points is None else np.asarray(points, dtype=np.float64)
        if pts.ndim != 2 or pts.shape[1] != 8:
            raise GeometryError(f"isolated points must have shape (P, 8), got {pts.shape}")
        ids = np.arange(len(pts)) if point_ids is None else np.asarray(point_ids, dtype=np.int64)
        if ids.shape != (len(pts),):
            raise GeometryError(f"point_ids must have shape ({len(pts)},), got {ids.shape}")
        if len(corners) == 0 and len(pts) == 0:
            raise GeometryError("the manifold has no triangle and no point to locate poses on")
        if method not in BLEND_METHODS:
            raise choice_error(GeometryError, "blend method", method, BLEND_METHODS)
        self.corners = corners
        self.points = pts
        self.point_ids = ids
        self.method = method
        self.orientation_scale = float(orientation_scale)
        self._point_tree = None
        if len(pts):
            feat = pose_features(pts, self.orientation_scale)
            self._point_tree = cKDTree(np.concatenate((feat, feat * _FLIP)), leafsize=self.LEAF)
        self._groups: list[tuple[np.ndarray, cKDTree, float]] = []
        #: Largest in-plane radius [m] of a triangle's bounding slab (0 without triangles).
        self.spacing = 0.0
        if len(corners):
            self._index_triangles(int(subdivisions))

    def _index_triangles(self, subdivisions: int) -> None:
        """The triangles' bounding slabs, size groups and KD-trees (see the class docstring)."""
        corners, method = self.corners, self.method
        t = len(corners)
        lat = _lattice(subdivisions)
        pts = blend(np.repeat(corners, len(lat), axis=0), np.tile(lat, (t, 1)), method)
        pts = pts.reshape(t, len(lat), 8)
        # features with the quaternion sign of each triangle's first corner
        ref = corners[:, 0, :4]
        sign = np.where(np.einsum("tpc,tc->tp", pts[..., :4], ref) < 0, -1.0, 1.0)
        feat = np.concatenate(
            (dq_translation(pts), (2.0 * self.orientation_scale) * sign[..., None] * pts[..., :4]),
            axis=-1,
        )  # (T, P, 7)
        centre = feat.mean(axis=1)
        rel = feat - centre[:, None]
        _, _, vt = np.linalg.svd(rel, full_matrices=False)
        basis = vt[:, :2]  # (T, 2, 7) best-fit plane
        inplane = np.einsum("tpk,tjk->tpj", rel, basis)
        normal = rel - np.einsum("tpj,tjk->tpk", inplane, basis)
        self._centre = centre
        self._basis = basis
        self._ref = ref
        self._radius = self.SAFETY * np.linalg.norm(inplane, axis=2).max(axis=1) + 1e-12
        self._thick = self.SAFETY * np.linalg.norm(normal, axis=2).max(axis=1) + 1e-12
        # in-plane coordinates of the corners (weights (1,0,0), (0,1,0), (0,0,1) are lattice points)
        first = [int(np.flatnonzero((lat == e).all(axis=1))[0]) for e in np.eye(3)]
        self._corner_xy = inplane[:, first]  # (T, 3, 2)
        # how far the points stray outside the corners' flat triangle in the plane
        outside = _point_triangle_2d(
            inplane.reshape(-1, 2), np.repeat(self._corner_xy, len(lat), axis=0)
        ).reshape(t, len(lat))
        scale = np.linalg.norm(
            self._corner_xy - self._corner_xy.mean(axis=1, keepdims=True), axis=2
        )
        self._bulge = self.SAFETY * outside.max(axis=1) + 1e-3 * scale.max(axis=1) + 1e-12
        # every point of a triangle is within this of its centre
        self._extent = np.hypot(self._radius, self._thick)
        # KD-trees over the centres (both signs) in the principal axes of the
        # centres: a rotation keeps every distance, and the trees' boxes follow
        # the thin manifold (ball queries about a third faster than on raw axes)
        both = np.concatenate((centre, centre * _FLIP))
        _, _, vt = np.linalg.svd(both - both.mean(axis=0), full_matrices=False)
        self._axes = vt.T  # (7, 7) orthogonal
        # groups of similar size, each with a KD-tree over its centres
        ratio = self._extent / np.median(self._extent)
        group = np.floor(np.log(np.maximum(ratio, 1e-3)) / np.log(self.GROUP)).astype(np.int64)
        group = np.maximum(group, -2)  # the smallest share one group
        self._groups = []
        for g in np.unique(group):
            members = np.flatnonzero(group == g)
            pts = np.concatenate((centre[members], centre[members] * _FLIP)) @ self._axes
            tree = cKDTree(pts, leafsize=self.LEAF)
            self._groups.append((members, tree, float(self._extent[members].max())))
        # a coarse lattice of every triangle's points, for the first upper bound,
        # and a KD-tree over all centres to pick the triangle
        up = _lattice(self.UPPER_SUBDIVISIONS)
        self._up_w = up
        self._up_dq = blend(
            np.repeat(corners, len(up), axis=0), np.tile(up, (t, 1)), method
        ).reshape(t, len(up), 8)
        self._centre_tree = cKDTree(both @ self._axes, leafsize=self.LEAF)
        self.spacing = float(self._radius.max())

    def __len__(self) -> int:
        """Number of triangles."""
        return len(self.corners)

    def __repr__(self) -> str:
        return (
            f"TriangleLocator({len(self)} triangles in {len(self._groups)} size groups, "
            f"{len(self.points)} isolated points, method={self.method!r}, "
            f"orientation_scale={self.orientation_scale} m/rad)"
        )

    def locate(
        self, queries: npt.ArrayLike, *, batch: int = 1024, exhaustive: bool = False
    ) -> Location:
        """Nearest point of the triangles to each query pose.

        Args:
            queries: (M, 8) unit dual quaternions (world), trusted.
            batch: Queries handled at once (bounds memory).
            exhaustive: Project every query onto every triangle, no pruning
                (the reference the pruned search equals; slow: M * T projections).

        Returns:
            The :class:`Location` of each query.
        """
        q = np.asarray(queries, dtype=np.float64).reshape(-1, 8)
        m = len(q)
        if exhaustive and len(self):
            batch = max(1, min(batch, 65536 // len(self)))
        tri = np.zeros(m, dtype=np.int64)
        w = np.zeros((m, 3))
        d = np.zeros(m)
        for a in range(0, m, batch):
            sl = slice(a, min(a + batch, m))
            tri[sl], w[sl], d[sl] = self._locate(q[sl], exhaustive)
        # isolated points are coded -1 - p in ``tri`` (below every triangle id)
        iso = tri < 0
        point = -1 - tri[iso]
        vertex = np.full(m, -1, dtype=np.int64)
        vertex[iso] = self.point_ids[point]
        dq = np.zeros((m, 8))
        on = ~iso
        if on.any():
            dq[on] = blend(self.corners[tri[on]], w[on], self.method)
        dq[iso] = self.points[point]
        tri[iso] = -1
        return Location(tri, w, d, dq, vertex)

    def _bounds(
        self, feat: np.ndarray, rows: np.ndarray, tris: np.ndarray, limit: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Lower bounds of (query, triangle) pairs whose bound is below ``limit``.

        Args:
            feat: (M, 7) query features (:func:`pose_features`).
            rows: (P,) query of each pair.
            tris: (P,) triangle of each pair.
            limit: (M,) per query: pairs bounded at or above it are dropped.

        Returns:
            ``(kept (K,), bound (K,), uv (K, 2))``: indices into the pairs, their
            lower bounds [m] and in-plane start weights ``(w1, w2)``.

        Why each is a lower bound of the distance from the query to every point
        ``y`` of the triangle (features taken with the sign of the triangle's
        first corner): the metric is ``min(|f+ - y|, |f- - y|)`` over the two
        signs of the query's rotation, so a lower bound of each sign's term
        bounds it.

        * Sphere: every ``y`` is within ``extent`` of the centre ``c``, so
          ``|f - y| >= |f - c| - extent`` (triangle inequality). The sign
          nearer to ``c`` (``s = sign(f_r . c_r)``) has ``|f_s - c|^2 =
          |f_-s - c|^2 - 4 |f_r . c_r|``, so its sphere bound is the smaller
          and bounds both terms: pairs with it at or above ``limit`` go.
        * Slab (near sign): ``y - c`` splits into an in-plane part of norm
          ``<= radius`` (and in the corners' flat triangle grown by ``bulge``)
          and an orthogonal part of norm ``<= thick``; ``f - c`` splits the
          same way into ``a`` and ``b``; by orthogonality ``|f - y|^2 =
          |a - y_a|^2 + |b - y_b|^2`` and each part is at least its norm gap
          (``|a| - radius`` or the distance to the grown flat triangle;
          ``|b| - thick``).
        * Far sign: its sphere bound ``|f_-s - c| - extent``.

        The bound is the smaller of the near sign's slab bound and the far
        sign's sphere bound. (Rounding, about 1e-17 m here, is far inside the
        1e-12 m added to every radius and thickness.)
        """
        f = feat[rows]
        rel = f - self._centre[tris]  # with the query's sign r_w >= 0
        dot = np.einsum("pk,pk->p", f[:, 3:], self._centre[tris, 3:])
        # the nearer sign: |-f_r - c_r|^2 = |f_r - c_r|^2 + 4 f_r . c_r
        near2 = np.einsum("pk,pk->p", rel, rel) + 4.0 * np.minimum(dot, 0.0)
        near2 = np.maximum(near2, 0.0)
        keep = np.flatnonzero(np.sqrt(near2) - self._extent[tris] < limit[rows])
        rel, near2, dot, tris = rel[keep], near2[keep], dot[keep], tris[keep]
        flip = np.flatnonzero(dot < 0)
        rel[flip, 3:] -= 2.0 * f[keep[flip], 3:]  # -f_r - c_r
        lim = limit[rows[keep]]
        a = np.einsum("pk,pjk->pj", rel, self._basis[tris])
        in2 = np.einsum("pj,pj->p", a, a)
        la = np.maximum(np.sqrt(in2) - self._radius[tris], 0.0)
        lb = np.maximum(np.sqrt(np.maximum(near2 - in2, 0.0)) - self._thick[tris], 0.0)
        bound = np.sqrt(la * la + lb * lb)
        refine = np.flatnonzero(bound < lim)
        if refine.size:
            t = tris[refine]
            flat = _point_triangle_2d(a[refine], self._corner_xy[t]) - self._bulge[t]
            la_r = np.maximum(la[refine], flat)
            bound[refine] = np.sqrt(la_r * la_r + lb[refine] * lb[refine])
        far = np.sqrt(near2 + 4.0 * np.abs(dot)) - self._extent[tris]
        bound = np.minimum(bound, np.maximum(far, 0.0))
        sel = np.flatnonzero(bound < lim)
        keep, bound, a, tris = keep[sel], bound[sel], a[sel], tris[sel]
        # start: the in-plane foot point in the corners' in-plane coordinates, clipped
        c = self._corner_xy[tris]
        e1, e2 = c[:, 1] - c[:, 0], c[:, 2] - c[:, 0]
        det = e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0]
        det = np.where(np.abs(det) > 1e-300, det, 1e-300)
        f = a - c[:, 0]
        u = (f[:, 0] * e2[:, 1] - f[:, 1] * e2[:, 0]) / det
        v = (e1[:, 0] * f[:, 1] - e1[:, 1] * f[:, 0]) / det
        w = np.clip(np.column_stack((1.0 - u - v, u, v)), 0.0, None)
        w /= np.maximum(w.sum(axis=1, keepdims=True), 1e-300)
        w[~np.isfinite(w).all(axis=1)] = 1.0 / 3.0
        return keep, bound, w[:, 1:]

    def _upper(self, q: np.ndarray, feat: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """A point of the manifold near each query: the first distance to beat.

        The nearest point of the coarse lattice of the triangle whose centre is
        nearest to the query; being a point of the manifold, its distance bounds
        the answer from above.

        Returns:
            ``(triangle (M,), weights (M, 3), distance (M,))``.
        """
        _, idx = self._centre_tree.query(feat @ self._axes, k=1)
        tri = idx % len(self)
        pts = self._up_dq[tri]  # (M, U, 8)
        d = pose_distance(pts, q[:, None, :], self.orientation_scale)
        j = np.argmin(d, axis=1)
        rows = np.arange(len(q))
        return tri, self._up_w[j], d[rows, j]

    def _nearest_point(
        self, q: np.ndarray, feat: np.ndarray, tri: np.ndarray, w: np.ndarray, d: np.ndarray
    ) -> None:
        """Where the nearest isolated point beats ``d``, it becomes the answer (``-1 - p``).

        The KD-tree holds both quaternion signs of the points' features, where
        the pose metric is Euclidean: its nearest neighbour is exact.
        """
        if self._point_tree is None:
            return
        _, idx = self._point_tree.query(feat, k=1)
        p = np.asarray(idx, dtype=np.int64) % len(self.points)
        dp = pose_distance(self.points[p], q, self.orientation_scale)
        closer = dp < d
        tri[closer] = -1 - p[closer]
        w[closer] = (1.0, 0.0, 0.0)
        d[closer] = dp[closer]

    def _locate(
        self, q: np.ndarray, exhaustive: bool = False
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        m = len(q)
        rows = np.arange(m)
        feat = pose_features(q, self.orientation_scale)
        # a point of the manifold near each query: an answer, and the distance to beat
        if len(self):
            best_tri, best_w, best_d = self._upper(q, feat)
        else:
            best_tri, best_w, best_d = np.zeros(m, np.int64), np.zeros((m, 3)), np.full(m, np.inf)
        self._nearest_point(q, feat, best_tri, best_w, best_d)
        if not len(self):
            return best_tri, best_w, best_d
        if exhaustive:
            r2 = np.repeat(rows, len(self))
            t2 = np.tile(np.arange(len(self)), m)
            kept, _, uv = self._bounds(feat, r2, t2, np.full(m, np.inf))
            self._project(q, r2[kept], t2[kept], uv, best_tri, best_w, best_d)
            return best_tri, best_w, best_d
        # every triangle whose centre is within best + its group's largest extent
        # (any other is farther than best by the sphere bound of _bounds; the
        # radii are a hair wider, as the rotated coordinates round differently)
        rot = feat @ self._axes
        r_list, t_list = [], []
        for members, tree, rmax in self._groups:
            radius = (best_d + rmax) * (1.0 + 1e-9)
            balls = tree.query_ball_point(rot, radius, return_sorted=False)
            counts = np.fromiter(map(len, balls), dtype=np.int64, count=m)
            ids = np.fromiter(itertools.chain.from_iterable(balls), np.int64, counts.sum())
            r_list.append(np.repeat(rows, counts))
            t_list.append(members[ids % len(members)])
        r2, t2 = _dedupe(np.concatenate(r_list), np.concatenate(t_list), len(self))
        kept, bound, uv = self._bounds(feat, r2, t2, best_d)
        r2, t2 = r2[kept], t2[kept]
        # per query in bound order: the lowest-bound triangles are projected
        # first, so the distance to beat falls before the rest are pruned
        # against it (a pair whose lower bound is at or above the distance
        # already found cannot hold a nearer point)
        order = np.lexsort((bound, r2))
        r2, t2, bound, uv = r2[order], t2[order], bound[order], uv[order]
        for _ in range(self.HEAD_PASSES):
            if not r2.size:
                break
            head = np.r_[True, r2[1:] != r2[:-1]]
            self._project(q, r2[head], t2[head], uv[head], best_tri, best_w, best_d)
            rest = np.flatnonzero(~head)
            rest = rest[bound[rest] < best_d[r2[rest]]]
            r2, t2, bound, uv = r2[rest], t2[rest], bound[rest], uv[rest]
        self._project(q, r2, t2, uv, best_tri, best_w, best_d)
        return best_tri, best_w, best_d

    def _project(
        self,
        q: np.ndarray,
        rows: np.ndarray,
        tris: np.ndarray,
        uv0: np.ndarray,
        best_tri: np.ndarray,
        best_w: np.ndarray,
        best_d: np.ndarray,
    ) -> None:
        """Project queries ``rows`` onto triangles ``tris``; keep the nearest per query."""
        if not rows.size:
            return
        w, d = project_onto_triangles(
            q[rows],
            self.corners[tris],
            uv0,
            method=self.method,
            orientation_scale=self.orientation_scale,
        )
        order = np.lexsort((tris, d, rows))  # per query: nearest, then lowest triangle
        rows, tris, w, d = rows[order], tris[order], w[order], d[order]
        head = np.r_[True, rows[1:] != rows[:-1]]
        rows, tris, w, d = rows[head], tris[head], w[head], d[head]
        better = (d < best_d[rows]) | ((d == best_d[rows]) & (tris < best_tri[rows]))
        rows = rows[better]
        best_tri[rows], best_w[rows], best_d[rows] = tris[better], w[better], d[better]
