"""The grasp rows as a mesh: which rows of the table are neighbours on the manifold.

Densification (uniform or adaptive) places every interpolated row at known
barycentric weights of one manifold triangle (``triangle``, ``vertices``,
``weights`` columns); candidates are the triangles' vertices. This module turns
that provenance back into a triangle mesh over the *rows*:

* every row is assigned to each manifold triangle it lies in (a candidate to
  all triangles around it, a row on an edge to both triangles of the edge);
* inside each manifold triangle its rows are triangulated by Delaunay in the
  triangle's barycentric coordinates, drawn as an equilateral triangle (a
  uniform lattice gives its regular cells; an adaptive one gives cells of
  several sizes, with no cell spanning a finer row);
* triangles with the same arrangement of rows (all of them, for a uniform
  lattice) share one triangulation.

Faces never cross a manifold edge, and rows on a shared edge are the same rows
on both sides, so the row mesh is conforming wherever densification is.
Neighbour edges (:attr:`RowMesh.edges`) feed IK continuity, patches and the
robustness margin; :func:`interpolate` evaluates row values anywhere on the
manifold (barycentric interpolation inside the face holding the point).
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
import numpy.typing as npt
from scipy.spatial import Delaunay, QhullError

from gcm_pipeline.errors import InputError
from gcm_pipeline.table import GraspTable

__all__ = ["RowMesh", "interpolate", "row_memberships", "row_mesh"]

_QUANT = float(1 << 30)  # weights are compared as integers of this resolution
_SQRT3_2 = np.sqrt(3.0) / 2.0


class RowMesh(NamedTuple):
    """A triangle mesh over the rows of a grasp table.

    Attributes:
        faces: (F, 3) int row ids of each face.
        triangle: (F,) int manifold triangle holding each face.
        weights: (F, 3, 3) barycentric weights of each face corner in that
            manifold triangle.
    """

    faces: np.ndarray
    triangle: np.ndarray
    weights: np.ndarray

    @property
    def edges(self) -> np.ndarray:
        """(E, 2) int unique neighbour pairs of rows, ``a < b``, sorted."""
        if not len(self.faces):
            return np.zeros((0, 2), dtype=np.int64)
        f = self.faces
        e = np.concatenate((f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]))
        e = np.sort(e, axis=1)
        return np.unique(e, axis=0)


def _equilateral(w: np.ndarray) -> np.ndarray:
    """Barycentric weights (..., 3) drawn in an equilateral triangle (..., 2)."""
    return np.stack((w[..., 1] + 0.5 * w[..., 2], _SQRT3_2 * w[..., 2]), axis=-1)


def row_memberships(
    grasps: GraspTable, triangles: npt.ArrayLike, n_candidates: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Every (row, manifold triangle) pair such that the row lies in the triangle.

    A candidate lies in every triangle around it, a row on an edge in both
    triangles of the edge, another interpolated row in its own triangle only.

    Args:
        grasps: The table (candidates first; ``vertices``, ``weights``,
            ``triangle`` for the other rows).
        triangles: (T, 3) the manifold's triangles.
        n_candidates: Number of candidate rows.

    Returns:
        ``(row (P,), triangle (P,), weights (P, 3))``, the weights in the
        order of the triangle's corners.
    """
    triangles = np.asarray(triangles, dtype=np.int64).reshape(-1, 3)
    t_count = len(triangles)
    n = len(grasps)
    rows = [triangles.reshape(-1)]
    tris = [np.repeat(np.arange(t_count), 3)]
    weights = [np.tile(np.eye(3), (t_count, 1))]
    if "vertices" in grasps and "weights" in grasps and n > n_candidates:
        vert = np.asarray(grasps["vertices"])[n_candidates:]
        w = np.asarray(grasps["weights"], dtype=np.float64)[n_candidates:]
        ids = np.arange(n_candidates, n)
        ok = (
            np.all((vert >= 0) & (vert < n_candidates), axis=1)
            & np.all(np.isfinite(w), axis=1)
            & np.all(w >= 0, axis=1)
        )
        vert, w, ids = vert[ok].astype(np.int64), w[ok], ids[ok]
        support = w > 0
        size = support.sum(axis=1)
        # rows on an edge belong to every triangle of that edge
        edge_rows = size == 2
        if edge_rows.any():
            ev, ew, eid = vert[edge_rows], w[edge_rows], ids[edge_rows]
            sup = support[edge_rows]
            pair = np.sort(ev[sup].reshape(-1, 2), axis=1)
            key = pair[:, 0] * n_candidates + pair[:, 1]
            tedge = np.sort(
                np.stack((triangles, np.roll(triangles, -1, axis=1)), axis=2).reshape(-1, 2),
                axis=1,
            )
            tkey = tedge[:, 0] * n_candidates + tedge[:, 1]
            tid = np.repeat(np.arange(t_count), 3)
            order = np.argsort(tkey, kind="stable")
            tkey, tid = tkey[order], tid[order]
            lo = np.searchsorted(tkey, key, side="left")
            hi = np.searchsorted(tkey, key, side="right")
            for offset in range(int((hi - lo).max(initial=0))):
                has = lo + offset < hi
                t = tid[lo[has] + offset]
                rows.append(eid[has])
                tris.append(t)
                weights.append(_reorder(ev[has], ew[has], triangles[t]))
        inner = size == 3
        if inner.any():
            tri_col = np.asarray(grasps["triangle"])[n_candidates:][ok][inner].astype(np.int64)
            valid = (tri_col >= 0) & (tri_col < t_count)
            t = tri_col[valid]
            rows.append(ids[inner][valid])
            tris.append(t)
            weights.append(_reorder(vert[inner][valid], w[inner][valid], triangles[t]))
    return np.concatenate(rows), np.concatenate(tris), np.concatenate(weights)


def _reorder(vert: np.ndarray, w: np.ndarray, corners: np.ndarray) -> np.ndarray:
    """Weights (P, 3) given for vertices ``vert`` (P, 3), in the order of ``corners`` (P, 3)."""
    match = vert[:, None, :] == corners[:, :, None]  # (P, corner, k)
    return np.einsum("pck,pk->pc", match, w)


def row_mesh(grasps: GraspTable, triangles: npt.ArrayLike, n_candidates: int) -> RowMesh:
    """Triangulate the rows of a densified table inside each manifold triangle.

    Args:
        grasps: The table: candidates first (rows ``0 .. n_candidates - 1``,
            the manifold's vertex ids), then interpolated rows with
            ``triangle``, ``vertices`` and ``weights``.
        triangles: (T, 3) the manifold's triangles (candidate row ids).
        n_candidates: Number of candidate rows.

    Returns:
        The :class:`RowMesh`.

    Raises:
        InputError: Triangles index rows that are not candidates.
    """
    tris = np.asarray(triangles, dtype=np.int64).reshape(-1, 3)
    if len(tris) and (tris.min() < 0 or tris.max() >= min(n_candidates, len(grasps))):
        raise InputError(
            f"manifold triangles index candidates outside 0..{min(n_candidates, len(grasps)) - 1}"
        )
    if not len(tris):
        return RowMesh(np.zeros((0, 3), np.int64), np.zeros(0, np.int64), np.zeros((0, 3, 3)))
    rows, tri, w = row_memberships(grasps, tris, n_candidates)
    quant = np.rint(w[:, 1:] * _QUANT).astype(np.int64)
    order = np.lexsort((quant[:, 1], quant[:, 0], tri))
    rows, tri, w, quant = rows[order], tri[order], w[order], quant[order]
    # drop a row listed twice in one triangle (same weights)
    dup = np.zeros(len(rows), dtype=bool)
    dup[1:] = (tri[1:] == tri[:-1]) & (quant[1:] == quant[:-1]).all(axis=1)
    rows, tri, w, quant = rows[~dup], tri[~dup], w[~dup], quant[~dup]
    bounds = np.searchsorted(tri, np.arange(len(tris) + 1))
    cache: dict[bytes, np.ndarray] = {}
    faces, face_tri, face_w = [], [], []
    for t in range(len(tris)):
        a, b = bounds[t], bounds[t + 1]
        key = quant[a:b].tobytes()
        local = cache.get(key)
        if local is None:
            local = _delaunay(w[a:b])
            cache[key] = local
        faces.append(rows[a:b][local])
        face_tri.append(np.full(len(local), t, dtype=np.int64))
        face_w.append(w[a:b][local])
    return RowMesh(
        np.concatenate(faces).astype(np.int64),
        np.concatenate(face_tri),
        np.concatenate(face_w),
    )


def _delaunay(w: np.ndarray) -> np.ndarray:
    """Local faces (F, 3), counter-clockwise, of points with barycentric weights (P, 3)."""
    if len(w) == 3:
        return np.array([[0, 1, 2]], dtype=np.int64)
    try:
        simplices = Delaunay(_equilateral(w)).simplices.astype(np.int64)
    except QhullError:  # pragma: no cover - three corners are always there
        return np.array([[0, 1, 2]], dtype=np.int64)
    xy = _equilateral(w)[simplices]
    e1, e2 = xy[:, 1] - xy[:, 0], xy[:, 2] - xy[:, 0]
    area = e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0]
    simplices = simplices[np.abs(area) > 1e-14]
    flip = area[np.abs(area) > 1e-14] < 0
    simplices[flip] = simplices[flip][:, [0, 2, 1]]
    return simplices


def interpolate(
    mesh: RowMesh, values: npt.ArrayLike, triangle: npt.ArrayLike, weights: npt.ArrayLike
) -> np.ndarray:
    """Values of rows interpolated at points of the manifold.

    Args:
        mesh: From :func:`row_mesh`.
        values: (N,) or (N, D) a value per row of the table.
        triangle: (M,) manifold triangle of each point.
        weights: (M, 3) barycentric weights of each point in its triangle.

    Returns:
        (M,) or (M, D): inside the row-mesh face holding the point, the
        barycentric blend of its corners' values (NaN where a needed corner
        value is NaN, or where the point is in no face).
    """
    vals = np.asarray(values, dtype=np.float64)
    tri = np.asarray(triangle, dtype=np.int64).reshape(-1)
    w = np.asarray(weights, dtype=np.float64).reshape(-1, 3)
    out = np.full((len(tri), *vals.shape[1:]), np.nan)
    if not len(tri) or not len(mesh.faces):
        return out
    order = np.argsort(mesh.triangle, kind="stable")
    ftri = mesh.triangle[order]
    fxy = _equilateral(mesh.weights[order])  # (F, 3, 2)
    faces = mesh.faces[order]
    pxy = _equilateral(w)
    lo = np.searchsorted(ftri, tri, side="left")
    hi = np.searchsorted(ftri, tri, side="right")
    point_order = np.argsort(tri, kind="stable")
    # group the points by triangle; one vectorised test per triangle
    starts = np.flatnonzero(np.r_[True, tri[point_order][1:] != tri[point_order][:-1]])
    ends = np.r_[starts[1:], len(tri)]
    for s, e in zip(starts, ends, strict=True):
        pts = point_order[s:e]
        a, b = lo[pts[0]], hi[pts[0]]
        if a == b:
            continue
        corners = fxy[a:b]  # (F, 3, 2)
        v0 = corners[:, 1] - corners[:, 0]
        v1 = corners[:, 2] - corners[:, 0]
        det = v0[:, 0] * v1[:, 1] - v0[:, 1] * v1[:, 0]
        d = pxy[pts][:, None, :] - corners[None, :, 0]  # (P, F, 2)
        l1 = (d[..., 0] * v1[:, 1] - d[..., 1] * v1[:, 0]) / det
        l2 = (v0[:, 0] * d[..., 1] - v0[:, 1] * d[..., 0]) / det
        bary = np.stack((1.0 - l1 - l2, l1, l2), axis=-1)  # (P, F, 3)
        worst = bary.min(axis=2)
        best = np.argmax(worst, axis=1)
        inside = worst[np.arange(len(pts)), best] >= -1e-9
        f = best[inside]
        lam = np.clip(bary[np.arange(len(pts))[inside], f], 0.0, 1.0)
        lam /= lam.sum(axis=1, keepdims=True)
        corner_vals = vals[faces[a:b][f]]  # (P, 3, ...)
        out[pts[inside]] = np.einsum("pk,pk...->p...", lam, corner_vals)
    return out
