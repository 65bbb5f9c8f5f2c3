r"""The continuous grasp manifold: blended triangles, a pose metric, nearest points.

A kept triangle with vertex poses :math:`\hat q_0, \hat q_1, \hat q_2` is a
*surface* of poses: every weight triple :math:`w` (barycentric, ``w >= 0``,
summing to 1) is the grasp :math:`S(w) = \mathrm{DLB}(w; \hat q_0, \hat q_1,
\hat q_2)` (or DIB). Densification samples it on a lattice; this module
evaluates it anywhere and finds the point of a set of such triangles nearest
to given poses.

Pose metric
-----------
Distances between poses ``a`` and ``b`` combine position [m] and orientation:

.. math::

    d(a, b)^2 = \lVert p_a - p_b \rVert^2
              + (2 L)^2 \min(\lVert r_a - r_b \rVert^2, \lVert r_a + r_b \rVert^2)

with ``r`` the unit rotation quaternions and ``L`` = :data:`ORIENTATION_SCALE`
= 0.1 m per radian. Since :math:`\lVert r_a - r_b \rVert = 2 \sin(\theta / 4)`
for a relative rotation angle :math:`\theta`, the orientation term is
:math:`L \cdot 4 \sin(\theta/4) = L \theta (1 - \theta^2/96 + \dots)`: a
rotation of 1 rad counts as 0.099 m (1 % less than ``L`` per radian at 1
rad, 10 % less at pi). ``L`` is about the distance from the grasp frame to the
wrist, so the term approximates how far the hand moves when the grasp turns
about its own origin. The metric is a true metric on poses (both quaternion
signs give the same value) and it is the Euclidean distance between the
embeddings ``[p, 2 L r]`` (:func:`pose_features`) of sign-aligned poses, so
KD-trees answer nearest-pose queries exactly.

Nearest points
--------------
:class:`TriangleLocator` answers "which point of the manifold is nearest to
this pose" for batches of queries:

1. every triangle is sampled on a small barycentric lattice
   (``subdivisions``), whose points (both quaternion signs) go into a KD-tree
   over the 7-D features;
2. the ``k`` nearest lattice points of a query name its candidate triangles;
3. on each candidate the query is projected onto the blend surface by a few
   sequential quadratic programming steps on the barycentric weights: the
   surface is linearised (DLB: analytic Jacobian of the normalised blend; DIB:
   finite differences) and the Gauss-Newton model is minimised exactly over
   the triangle (interior, else the best point of the three edges);
4. a query whose ``k``-th lattice neighbour is not farther than the best
   distance found plus the lattice spacing ``h`` might have missed a triangle:
   every lattice point within that radius adds its triangle and step 3 runs
   again for them. Any point of a triangle lies within ``h`` of one of its
   lattice points, so the answer is the nearest of all triangles' local
   minima.
"""

from __future__ import annotations

import itertools
from typing import NamedTuple

import numpy as np
import numpy.typing as npt
from scipy.spatial import cKDTree

from gcm_pipeline.errors import GeometryError, unknown_choice
from gcm_pipeline.geometry.dualquat import _cross, dib, dlb, quat_mul

__all__ = [
    "BLEND_METHODS",
    "ORIENTATION_SCALE",
    "Location",
    "TriangleLocator",
    "blend",
    "pose_distance",
    "pose_features",
    "project_onto_triangles",
]

#: Length scale ``L`` [m/rad] of the orientation term of the pose metric.
ORIENTATION_SCALE = 0.1

BLEND_METHODS = ("dib", "dlb")

_QCONJ = np.array([1.0, -1.0, -1.0, -1.0])


class Location(NamedTuple):
    """Nearest manifold points of M query poses.

    Attributes:
        triangle: (M,) int index of the triangle holding the nearest point.
        weights: (M, 3) barycentric weights of that point in its triangle.
        distance: (M,) pose-metric distance [m] from the query to it.
        dq: (M, 8) the nearest point itself (unit dual quaternion, world).
    """

    triangle: np.ndarray
    weights: np.ndarray
    distance: np.ndarray
    dq: np.ndarray


def blend(corners: np.ndarray, weights: np.ndarray, method: str = "dlb") -> np.ndarray:
    """Poses (M, 8) of barycentric weights (M, 3) in triangles with corners (M, 3, 8).

    A weight row with a single 1 returns that corner bit for bit (the
    triangle's vertex), whatever the method.

    Raises:
        GeometryError: Unknown method (the weights are trusted: >= 0, sum 1).
    """
    if method not in BLEND_METHODS:
        raise GeometryError(unknown_choice("blend method", method, BLEND_METHODS))
    corners = np.asarray(corners, dtype=np.float64)
    weights = np.asarray(weights, dtype=np.float64)
    if method == "dlb":
        out = dlb(corners, weights, check=False)
    else:
        out = dib(corners, weights, check=False)
    vertex = weights == 1.0
    rows = np.flatnonzero(vertex.any(axis=1))
    if rows.size:
        out[rows] = corners[rows, np.argmax(vertex[rows], axis=1)]
    return out


def pose_features(dq: npt.ArrayLike, orientation_scale: float = ORIENTATION_SCALE) -> np.ndarray:
    """Embeddings ``[p, 2 L r]`` (..., 7) of poses (..., 8), ``r_w >= 0``.

    The metric of the module docstring is the Euclidean distance between
    embeddings of sign-aligned poses; use both signs of ``r`` in a KD-tree.
    """
    dq = np.asarray(dq, dtype=np.float64)
    r = dq[..., :4]
    sign = np.where(r[..., :1] < 0, -1.0, 1.0)
    return np.concatenate((_translation(dq), (2.0 * orientation_scale) * sign * r), axis=-1)


def pose_distance(
    a: npt.ArrayLike, b: npt.ArrayLike, orientation_scale: float = ORIENTATION_SCALE
) -> np.ndarray:
    """Pose-metric distance [m] (...,) between poses (..., 8) (see the module docstring)."""
    a = np.asarray(a, dtype=np.float64)
    b = np.asarray(b, dtype=np.float64)
    dp = _translation(a) - _translation(b)
    ra, rb = a[..., :4], b[..., :4]
    sign = np.where(np.einsum("...i,...i->...", ra, rb) < 0, -1.0, 1.0)[..., None]
    dr = ra - sign * rb  # the nearer of rb and -rb (no cancellation at small angles)
    chord2 = np.einsum("...i,...i->...", dr, dr)
    return np.sqrt(np.einsum("...i,...i->...", dp, dp) + (2.0 * orientation_scale) ** 2 * chord2)


def _translation(dq: np.ndarray) -> np.ndarray:
    w, v = dq[..., 0:1], dq[..., 1:4]
    dw, dv = dq[..., 4:5], dq[..., 5:8]
    return 2.0 * (w * dv - dw * v + _cross(v, dv))


# --------------------------------------------------------------------------- projection
def _dlb_model(
    corners: np.ndarray, uv: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """DLB surface at ``uv`` (P, 2): position (P, 3), rotation (P, 4) and their Jacobians.

    ``w = (1 - u - v, u, v)``; signs aligned to the heaviest corner as
    :func:`~gcm_pipeline.geometry.dualquat.dlb` does. The blend ``b`` is
    affine in (u, v); ``r = b_r / |b_r|`` and ``p = vec(2 b_d b_r^*) / |b_r|^2``.

    Returns:
        ``p`` (P, 3), ``r`` (P, 4), ``dp`` (P, 3, 2), ``dr`` (P, 4, 2).
    """
    w = np.column_stack((1.0 - uv[:, 0] - uv[:, 1], uv[:, 0], uv[:, 1]))
    piv = np.argmax(w, axis=1)
    rpiv = corners[np.arange(len(w)), piv, :4]
    sign = np.where(np.einsum("pkc,pc->pk", corners[:, :, :4], rpiv) < 0, -1.0, 1.0)
    c = corners * sign[:, :, None]
    b = np.einsum("pk,pkc->pc", w, c)
    db = np.stack((c[:, 1] - c[:, 0], c[:, 2] - c[:, 0]), axis=-1)  # (P, 8, 2)
    a, e = b[:, :4], b[:, 4:]
    da, de = db[:, :4], db[:, 4:]
    n2 = np.einsum("pc,pc->p", a, a)
    n = np.sqrt(n2)
    r = a / n[:, None]
    a_conj = a * _QCONJ
    m = 2.0 * quat_mul(e, a_conj)  # 2 e a*, its vector part / n2 is p
    p = m[:, 1:] / n2[:, None]
    dn2 = 2.0 * np.einsum("pc,pcj->pj", a, da)  # (P, 2)
    dp = np.empty((len(w), 3, 2))
    dr = np.empty((len(w), 4, 2))
    for j in range(2):
        dm = 2.0 * (quat_mul(de[:, :, j], a_conj) + quat_mul(e, da[:, :, j] * _QCONJ))
        dp[:, :, j] = (dm[:, 1:] - p * dn2[:, j : j + 1]) / n2[:, None]
        dr[:, :, j] = da[:, :, j] / n[:, None] - r * (0.5 * dn2[:, j] / n2)[:, None]
    return p, r, dp, dr


def _dib_model(
    corners: np.ndarray, uv: np.ndarray, step: float = 1e-6
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """As :func:`_dlb_model` for DIB, Jacobians by forward differences (inward)."""
    w = np.column_stack((1.0 - uv[:, 0] - uv[:, 1], uv[:, 0], uv[:, 1]))
    base = dib(corners, w, check=False)
    p, r = _translation(base), base[:, :4]
    dp = np.empty((len(w), 3, 2))
    dr = np.empty((len(w), 4, 2))
    for j in range(2):
        h = np.where(uv.sum(axis=1) + step > 1.0, -step, step)  # stay inside the triangle
        wj = w.copy()
        wj[:, j + 1] += h
        wj[:, 0] -= h
        moved = dib(corners, wj, check=False)
        rj = moved[:, :4] * np.where(np.einsum("pc,pc->p", moved[:, :4], r) < 0, -1.0, 1.0)[:, None]
        dp[:, :, j] = (_translation(moved) - p) / h[:, None]
        dr[:, :, j] = (rj - r) / h[:, None]
    return p, r, dp, dr


def _qp_triangle(x: np.ndarray, h: np.ndarray, g: np.ndarray) -> np.ndarray:
    """Minimise ``0.5 d^T H d + g^T d`` over ``x + d`` in the triangle u, v >= 0, u + v <= 1.

    Args:
        x: Current points (P, 2).
        h: Hessians (P, 2, 2), positive semi-definite.
        g: Gradients (P, 2).

    Returns:
        The minimisers (P, 2), exact for the quadratic model.
    """
    reg = 1e-12 * (np.trace(h, axis1=1, axis2=2) + 1e-30)
    hh = h + reg[:, None, None] * np.eye(2)
    det = hh[:, 0, 0] * hh[:, 1, 1] - hh[:, 0, 1] * hh[:, 1, 0]
    inv = (
        np.stack(
            (
                np.stack((hh[:, 1, 1], -hh[:, 0, 1]), axis=-1),
                np.stack((-hh[:, 1, 0], hh[:, 0, 0]), axis=-1),
            ),
            axis=1,
        )
        / det[:, None, None]
    )
    free = x - np.einsum("pij,pj->pi", inv, g)
    inside = (free[:, 0] >= 0) & (free[:, 1] >= 0) & (free.sum(axis=1) <= 1)
    out = free
    if inside.all():
        return out
    rows = np.flatnonzero(~inside)
    xr, hr, gr = x[rows], h[rows], g[rows]
    corners = np.array([[0.0, 0.0], [1.0, 0.0], [0.0, 1.0]])
    best = np.full(len(rows), np.inf)
    best_pt = np.zeros((len(rows), 2))
    for a_i, b_i in ((0, 1), (1, 2), (2, 0)):
        a, b = corners[a_i], corners[b_i]
        # point a + s (b - a); model value as a quadratic in s
        d0 = a - xr  # step to a
        e = b - a
        he = np.einsum("pij,j->pi", hr, e)
        curv = np.einsum("j,pj->p", e, he)
        slope = np.einsum("pj,pj->p", gr, np.broadcast_to(e, gr.shape)) + np.einsum(
            "pj,pj->p", d0, he
        )
        s = np.clip(np.where(curv > 0, -slope / np.where(curv > 0, curv, 1.0), 0.0), 0.0, 1.0)
        # with zero curvature pick the better end
        flat = curv <= 0
        s = np.where(flat, np.where(slope < 0, 1.0, 0.0), s)
        pt = a + s[:, None] * e
        d = pt - xr
        val = 0.5 * np.einsum("pi,pij,pj->p", d, hr, d) + np.einsum("pi,pi->p", gr, d)
        better = val < best
        best = np.where(better, val, best)
        best_pt[better] = pt[better]
    out = out.copy()
    out[rows] = best_pt
    return out


def project_onto_triangles(
    queries: np.ndarray,
    corners: np.ndarray,
    uv0: np.ndarray,
    *,
    method: str = "dlb",
    orientation_scale: float = ORIENTATION_SCALE,
    iterations: int = 8,
    tolerance: float = 1e-8,
) -> tuple[np.ndarray, np.ndarray]:
    """Nearest point of each blended triangle to a query pose (local minimum, batched).

    Args:
        queries: (P, 8) query poses, one per pair.
        corners: (P, 3, 8) the triangle's vertex poses, one per pair.
        uv0: (P, 2) starting weights ``(w1, w2)`` (e.g. of the nearest lattice point).
        method: The blend, ``dlb`` or ``dib``.
        orientation_scale: ``L`` [m/rad] of the pose metric.
        iterations: Maximum SQP steps.
        tolerance: Stop when no pair moves more than this in (u, v).

    Returns:
        ``(weights (P, 3), distance (P,))``: the local minimiser and its
        pose-metric distance [m] (from the exact blend, :func:`blend`).
    """
    model = _dlb_model if method == "dlb" else _dib_model
    uv = np.array(uv0, dtype=np.float64)
    p_q = _translation(queries)
    r_q = queries[:, :4]
    scale = 2.0 * orientation_scale
    active = np.arange(len(uv))
    for _ in range(iterations):
        if not active.size:
            break
        p, r, dp, dr = model(corners[active], uv[active])
        sign = np.where(np.einsum("pc,pc->p", r, r_q[active]) < 0, -1.0, 1.0)
        res = np.concatenate((p - p_q[active], scale * (r - sign[:, None] * r_q[active])), axis=1)
        jac = np.concatenate((dp, scale * dr), axis=1)  # (P, 7, 2)
        h = np.einsum("pki,pkj->pij", jac, jac)
        g = np.einsum("pki,pk->pi", jac, res)
        new = _qp_triangle(uv[active], h, g)
        moved = np.abs(new - uv[active]).max(axis=1)
        uv[active] = new
        active = active[moved > tolerance]
    w = np.column_stack((1.0 - uv[:, 0] - uv[:, 1], uv[:, 0], uv[:, 1]))
    w = np.clip(w, 0.0, 1.0)
    w /= w.sum(axis=1, keepdims=True)
    w = _snap(w)
    pts = blend(corners, w, method)
    return w, pose_distance(pts, queries, orientation_scale)


def _snap(w: np.ndarray, eps: float = 1e-12) -> np.ndarray:
    """Weights within ``eps`` of 0 or 1 set exactly (vertices and edges come out exact)."""
    w = np.where(w < eps, 0.0, w)
    w = np.where(w > 1.0 - eps, 1.0, w)
    return w / w.sum(axis=1, keepdims=True)


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


class TriangleLocator:
    """Batched nearest-point queries on a set of blended triangles.

    Each triangle is cut into ``subdivisions**2`` cells; a cell's centroid
    pose and radius (the largest pose distance from the centroid to its
    corners, times :attr:`SAFETY` for the curvature of the blend) bound the
    distance from a query to any point of the cell from below. A query is
    projected onto every triangle having a cell whose bound is below the
    distance to the nearest centroid (which is a point of the manifold), so
    no triangle that could hold the nearest point is left out.

    Args:
        corners: (T, 3, 8) vertex poses of the T triangles (world).
        method: The blend, ``dlb`` or ``dib``.
        orientation_scale: ``L`` [m/rad] of the pose metric.
        subdivisions: Cells per triangle edge.
        neighbours: Cells looked up per query before the bound decides
            whether more are needed.

    Raises:
        GeometryError: No triangle, wrong shapes, unknown method.
    """

    #: Factor on the cells' corner distances covering the blend's curvature.
    SAFETY = 1.25

    def __init__(
        self,
        corners: npt.ArrayLike,
        *,
        method: str = "dlb",
        orientation_scale: float = ORIENTATION_SCALE,
        subdivisions: int = 6,
        neighbours: int = 16,
    ) -> None:
        corners = np.asarray(corners, dtype=np.float64)
        if corners.ndim != 3 or corners.shape[1:] != (3, 8):
            raise GeometryError(f"triangle corners must have shape (T, 3, 8), got {corners.shape}")
        if len(corners) == 0:
            raise GeometryError("the manifold has no triangle to locate poses on")
        if method not in BLEND_METHODS:
            raise GeometryError(unknown_choice("blend method", method, BLEND_METHODS))
        self.corners = corners
        self.method = method
        self.orientation_scale = float(orientation_scale)
        self.neighbours = max(1, int(neighbours))
        centroid_w, corner_w = _cells(int(subdivisions))
        t, c = len(corners), len(centroid_w)
        tri = np.repeat(np.arange(t), c)
        centres = blend(corners[tri], np.tile(centroid_w, (t, 1)), method)
        ends = blend(
            np.repeat(corners[tri], 3, axis=0), np.tile(corner_w.reshape(-1, 3), (t, 1)), method
        ).reshape(t * c, 3, 8)
        radius = self.SAFETY * pose_distance(centres[:, None, :], ends, self.orientation_scale).max(
            axis=1
        )
        feat = pose_features(centres, self.orientation_scale)
        flipped = feat.copy()
        flipped[:, 3:] *= -1.0
        self._tree = cKDTree(np.concatenate((feat, flipped)))
        self._tri = np.concatenate((tri, tri))
        uv = np.tile(centroid_w[:, 1:], (t, 1))
        self._uv = np.concatenate((uv, uv))
        self._radius = np.concatenate((radius, radius))
        #: Largest cell radius [m] (pose metric).
        self.spacing = float(radius.max())

    def __len__(self) -> int:
        """Number of triangles."""
        return len(self.corners)

    def __repr__(self) -> str:
        return (
            f"TriangleLocator({len(self)} triangles, method={self.method!r}, "
            f"orientation_scale={self.orientation_scale} m/rad, cell radius <= "
            f"{self.spacing:.3g} m)"
        )

    def locate(self, queries: npt.ArrayLike, *, batch: int = 4096) -> Location:
        """Nearest point of the triangles to each query pose.

        Args:
            queries: (M, 8) unit dual quaternions (world), trusted.
            batch: Queries handled at once (bounds memory).

        Returns:
            The :class:`Location` of each query.
        """
        q = np.asarray(queries, dtype=np.float64).reshape(-1, 8)
        m = len(q)
        tri = np.zeros(m, dtype=np.int64)
        w = np.zeros((m, 3))
        d = np.zeros(m)
        for a in range(0, m, batch):
            sl = slice(a, min(a + batch, m))
            tri[sl], w[sl], d[sl] = self._locate(q[sl])
        dq = blend(self.corners[tri], w, self.method) if m else np.zeros((0, 8))
        return Location(tri, w, d, dq)

    def _locate(self, q: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        m = len(q)
        feat = pose_features(q, self.orientation_scale)
        d0, nearest = self._tree.query(feat, k=1)  # a point of the manifold: an upper bound
        # stage 1: project onto the triangle of the nearest cell, a tighter bound d1
        t1 = self._tri[nearest]
        w1, d1 = project_onto_triangles(
            q,
            self.corners[t1],
            self._uv[nearest],
            method=self.method,
            orientation_scale=self.orientation_scale,
        )
        # stage 2: every other triangle with a cell whose lower bound |q - c| - rho is below d1
        balls = self._tree.query_ball_point(feat, d1 + self.spacing)
        counts = np.fromiter((len(b) for b in balls), dtype=np.int64, count=m)
        rows = np.repeat(np.arange(m), counts)
        cell = np.fromiter(itertools.chain.from_iterable(balls), np.int64, counts.sum())
        dist = np.linalg.norm(self._tree.data[cell] - feat[rows], axis=1)
        tri = self._tri[cell]
        keep = (dist - self._radius[cell] < d1[rows]) & (tri != t1[rows])
        rows, cell, dist, tri = rows[keep], cell[keep], dist[keep], tri[keep]
        # one projection per (query, triangle), started at its nearest cell
        order = np.lexsort((dist, tri, rows))
        rows, cell, tri = rows[order], cell[order], tri[order]
        head = np.ones(len(rows), dtype=bool)
        head[1:] = (rows[1:] != rows[:-1]) | (tri[1:] != tri[:-1])
        pr, pt, uv0 = rows[head], tri[head], self._uv[cell[head]]
        w, d = project_onto_triangles(
            q[pr],
            self.corners[pt],
            uv0,
            method=self.method,
            orientation_scale=self.orientation_scale,
        )
        pr = np.concatenate((np.arange(m), pr))
        pt = np.concatenate((t1, pt))
        w = np.concatenate((w1, w))
        d = np.concatenate((d1, d))
        order = np.lexsort((pt, d, pr))  # per query: smallest distance, then lowest triangle
        pr, pt, w, d = pr[order], pt[order], w[order], d[order]
        first = np.ones(len(pr), dtype=bool)
        first[1:] = pr[1:] != pr[:-1]
        best_tri = np.zeros(m, dtype=np.int64)
        best_w = np.zeros((m, 3))
        best_d = np.full(m, np.inf)
        best_tri[pr[first]] = pt[first]
        best_w[pr[first]] = w[first]
        best_d[pr[first]] = d[first]
        return best_tri, best_w, best_d
