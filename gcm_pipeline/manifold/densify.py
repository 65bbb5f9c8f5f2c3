r"""Densify stage: new grasp poses inside every kept triangle of the manifold.

Inside a triangle with vertices :math:`(v_0, v_1, v_2)` and ``n`` subdivisions
the barycentric weights form the regular lattice

.. math:: w = (i, j, k) / n, \qquad i + j + k = n, \quad i, j, k \ge 0,

``(n + 1)(n + 2) / 2`` points of which three are the vertices themselves.
Each weight triple is blended by DLB (default) or DIB
(:mod:`gcm_pipeline.geometry.dualquat`) of the three vertex poses. With the
standard dual quaternion convention this is what the paper intends: the
vertices are reproduced exactly and the interior varies smoothly.

Points on an edge shared by two triangles, and the vertices, appear once:
edge points are identified by integer keys ``(low vertex id, high vertex id,
p, q)``, the position ``p / q`` (reduced fraction) along the edge from the
lower id, so triangles with different ``n`` (``spacing`` mode) share the
points they have in common. An edge point belongs to the first triangle (in
manifold order) that has it. No floats are compared.

Output table: the N candidate rows first, in input order and bit-for-bit
(also candidates no kept triangle uses), then the interpolated rows, by
triangle and, inside a triangle, edge points before interior points.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from gcm_pipeline.bounds import check_size, lattice_size
from gcm_pipeline.errors import GeometryError, InputError, choice_error
from gcm_pipeline.geometry.dualquat import dq_translation
from gcm_pipeline.geometry.pose_blend import dib, dlb
from gcm_pipeline.manifold.build import Manifold, candidate_poses
from gcm_pipeline.table import GraspTable, candidate_fill

__all__ = ["DENSIFY_METHODS", "densify", "fill_column", "lattice_counts"]

DENSIFY_METHODS = ("dib", "dlb")

_OWN_COLUMNS = ("dq", "origin", "triangle", "vertices", "weights")
_MAX_SUBDIVISIONS = 1 << 15


def lattice_counts(n: int) -> tuple[int, int, int]:
    """Points of an ``n``-subdivided triangle: (vertices, per edge, interior)."""
    return 3, n - 1, (n - 1) * (n - 2) // 2


def _lattice(n: int) -> tuple[np.ndarray, np.ndarray]:
    """Integer lattice points (P, 3) of one triangle without its vertices, and edge ids.

    Returns:
        ``(ijk, edge)``: counts per vertex (summing to ``n``) and, per point,
        the edge it lies on (0: v0-v1, 1: v1-v2, 2: v2-v0) or -1 (interior).
        Edge points come first (edge by edge, walking from its first vertex),
        then interior points row by row.
    """
    m = np.arange(1, n, dtype=np.int64)
    zero = np.zeros_like(m)
    edges = [
        np.stack((n - m, m, zero), axis=1),  # v0 -> v1
        np.stack((zero, n - m, m), axis=1),  # v1 -> v2
        np.stack((m, zero, n - m), axis=1),  # v2 -> v0
    ]
    i, j = np.meshgrid(np.arange(1, n), np.arange(1, n), indexing="ij")
    k = n - i - j
    inner = k >= 1
    interior = np.stack((i[inner], j[inner], k[inner]), axis=1)
    ijk = np.concatenate([*edges, interior])
    edge = np.concatenate([np.full(len(m), e) for e in range(3)] + [np.full(len(interior), -1)])
    return ijk.reshape(-1, 3), edge.astype(np.int64)


def _subdivisions(
    pos: np.ndarray, tris: np.ndarray, subdivisions: int | None, spacing: float | None
) -> np.ndarray:
    """Subdivisions per triangle (T,): ``subdivisions`` or from the longest edge / ``spacing``."""
    if spacing is not None:
        spacing = float(spacing)
        if not (np.isfinite(spacing) and spacing > 0):
            raise GeometryError(f"densify spacing must be a positive length [m], got {spacing!r}")
        p = pos[tris]
        longest = np.linalg.norm(p - np.roll(p, -1, axis=1), axis=2).max(axis=1)
        n = np.maximum(np.ceil(longest / spacing - 1e-9), 1)  # float: checked before int64
        if len(n) and n.max() > _MAX_SUBDIVISIONS:
            most = f"{int(n.max()):,}" if n.max() < 1e15 else f"{n.max():.3g}"
            raise GeometryError(
                f"densify spacing {spacing!r} m asks for {most} subdivisions of a "
                f"triangle (max {_MAX_SUBDIVISIONS:,})"
            )
        return n.astype(np.int64)
    if subdivisions is None:
        raise GeometryError("densify needs subdivisions or spacing, got neither")
    if isinstance(subdivisions, bool) or int(subdivisions) != subdivisions or subdivisions < 1:
        raise GeometryError(f"densify subdivisions must be an integer >= 1, got {subdivisions!r}")
    if subdivisions > _MAX_SUBDIVISIONS:
        raise GeometryError(
            f"densify subdivisions must be <= {_MAX_SUBDIVISIONS}, got {subdivisions!r}"
        )
    return np.full(len(tris), int(subdivisions), dtype=np.int64)


def _points_uniform(tris: np.ndarray, n: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """:func:`_points` when every triangle has the same ``n``: dedupe whole edges.

    With one lattice on every edge, two triangles sharing an edge share all
    its points; the edge (low id, high id) belongs to its first triangle.
    """
    ijk, edge = _lattice(n)
    t_count, p = len(tris), len(ijk)
    lo = np.minimum(tris, np.roll(tris, -1, axis=1)).ravel()
    hi = np.maximum(tris, np.roll(tris, -1, axis=1)).ravel()
    order = np.lexsort((np.arange(len(lo)), hi, lo))  # first triangle first per edge
    first = np.ones(len(lo), dtype=bool)
    first[order[1:]] = (lo[order[1:]] != lo[order[:-1]]) | (hi[order[1:]] != hi[order[:-1]])
    owner = first.reshape(t_count, 3)  # (T, 3): does triangle t own its edge e?
    keep_tp = np.ones((t_count, p), dtype=bool)
    on_edge = edge >= 0
    keep_tp[:, on_edge] = owner[:, edge[on_edge]]
    tri = np.repeat(np.arange(t_count, dtype=np.int64), p).reshape(t_count, p)[keep_tp]
    local = np.broadcast_to(np.arange(p), (t_count, p))[keep_tp]
    return tri, ijk[local], np.full(len(tri), n, dtype=np.int64)


def _points(tris: np.ndarray, n_per: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Deduplicated lattice points of all triangles.

    Returns:
        ``(tri, ijk, n)``: owner triangle (M,), lattice counts (M, 3) and the
        owner's subdivisions (M,), ordered by triangle then lattice order.
    """
    groups = np.unique(n_per)
    if len(groups) == 1:
        return _points_uniform(tris, int(groups[0]))
    return _points_general(tris, n_per)


def _points_general(
    tris: np.ndarray, n_per: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """:func:`_points` for any subdivisions per triangle: dedupe by edge-point keys."""
    tri_parts, ijk_parts, local_parts, edge_parts = [], [], [], []
    for n in np.unique(n_per):  # a loop over distinct subdivisions, not triangles
        ts = np.flatnonzero(n_per == n)
        ijk, edge = _lattice(int(n))
        if not len(ijk):
            continue
        p = len(ijk)
        tri_parts.append(np.repeat(ts, p))
        ijk_parts.append(np.tile(ijk, (len(ts), 1)))
        local_parts.append(np.tile(np.arange(p), len(ts)))
        edge_parts.append(np.tile(edge, len(ts)))
    if not tri_parts:
        empty = np.zeros(0, dtype=np.int64)
        return empty, np.zeros((0, 3), dtype=np.int64), empty
    tri = np.concatenate(tri_parts)
    ijk = np.concatenate(ijk_parts)
    local = np.concatenate(local_parts)
    edge = np.concatenate(edge_parts)
    n = n_per[tri]

    # Canonical keys of edge points: (low id, high id, p, q), p/q along low -> high.
    on_edge = edge >= 0
    te, ee = tri[on_edge], edge[on_edge]
    a = tris[te, ee]
    b = tris[te, (ee + 1) % 3]
    wb = ijk[on_edge][np.arange(len(ee)), (ee + 1) % 3]  # count of the edge's second vertex
    lo, hi = np.minimum(a, b), np.maximum(a, b)
    num = np.where(a == lo, wb, n[on_edge] - wb)
    den = n[on_edge]
    g = np.gcd(num, den)
    num, den = num // g, den // g
    keep = np.ones(len(tri), dtype=bool)
    if len(te):
        order = np.lexsort((local[on_edge], te, den, num, hi, lo))
        key = np.stack((lo, hi, num, den), axis=1)[order]
        dup = np.concatenate(([False], (key[1:] == key[:-1]).all(axis=1)))
        edge_rows = np.flatnonzero(on_edge)
        keep[edge_rows[order[dup]]] = False
    final = np.lexsort((local[keep], tri[keep]))
    return tri[keep][final], ijk[keep][final], n[keep][final]


def fill_column(
    column: np.ndarray, count: int, rule: str = "missing", vertices: Any = None, weights: Any = None
) -> np.ndarray:
    """Values for ``count`` interpolated rows of an extra candidate column.

    ``rule`` ``blend`` (float columns only) blends the vertices' values with
    the barycentric weights; anything else gives the dtype's missing value.
    """
    shape = (count, *column.shape[1:])
    kind = column.dtype.kind
    if rule == "blend" and kind == "f" and vertices is not None:
        w = np.asarray(weights, dtype=float).reshape((count, 3) + (1,) * (column.ndim - 1))
        # a vertex of weight 0 does not count, even if its value is NaN
        terms = np.where(w > 0, w * column[vertices], 0.0)
        return np.sum(terms, axis=1).astype(column.dtype, copy=False)
    if kind == "f" or kind == "c":
        return np.full(shape, np.nan, dtype=column.dtype)
    if kind in "iu":
        return np.full(shape, -1 if kind == "i" else 0, dtype=column.dtype)
    if kind == "b":
        return np.zeros(shape, dtype=bool)
    if kind in "US":
        return np.full(shape, "", dtype=column.dtype)
    return np.full(shape, None, dtype=object)


def densify(
    grasps: GraspTable,
    manifold: Manifold | Any,
    *,
    subdivisions: int | None = 4,
    spacing: float | None = None,
    method: str = "dlb",
    max_poses: int | None = None,
) -> GraspTable:
    """Add blended grasp poses on a barycentric lattice inside every kept triangle.

    Args:
        grasps: The candidate table (``dq`` (N, 8)); the manifold's triangles
            index its rows.
        manifold: From :func:`gcm_pipeline.manifold.build.build_manifold`
            (anything with ``triangles`` (T, 3)).
        subdivisions: Lattice subdivisions ``n`` per triangle edge (>= 1); a
            triangle then yields ``(n + 1)(n + 2) / 2`` points with its vertices.
        spacing: If given [m], ``n`` per triangle is ``ceil(longest edge /
            spacing)`` (overrides ``subdivisions``).
        method: ``dlb`` (dual quaternion linear blending, default) or ``dib``
            (iterative bi-invariant blending).
        max_poses: Ceiling of the output rows (``densify.max_poses``), checked
            on an upper bound of the lattice before it is built (None: no ceiling).

    Returns:
        A table of M rows: the N candidates (input order, poses bit-for-bit),
        then the interpolated poses. Columns ``dq`` (M, 8), ``origin`` (M,)
        ``candidate``/``interpolated``, ``triangle`` (M,) index into
        ``manifold.triangles`` (-1 for candidates), ``vertices`` (M, 3)
        candidate row ids (-1 for candidates), ``weights`` (M, 3) barycentric
        weights of the vertices (NaN for candidates). Other columns of
        ``grasps`` (per-candidate columns such as ``score``, ``width``,
        ``source_id``) are kept for the candidate rows and filled for the
        interpolated ones by their rule
        (:func:`gcm_pipeline.table.candidate_fill`): ``blend`` columns
        (``score``, ``width``) get the barycentric blend of the three vertex
        values, the others NaN, -1, False, ``""`` or None by dtype.

    Raises:
        GeometryError: On an unknown method, invalid subdivisions or
            spacing, invalid poses, or triangles indexing rows that do not exist.
        InputError: If ``grasps`` has no ``dq`` column.
    """
    if method not in DENSIFY_METHODS:
        raise choice_error(GeometryError, "densify method", method, DENSIFY_METHODS)
    if "dq" not in grasps:
        raise InputError(f"grasp table has no column 'dq'; columns: {', '.join(grasps.columns)}")
    dq_in = np.asarray(grasps["dq"])
    dq = candidate_poses(grasps)
    tris = np.asarray(manifold.triangles, dtype=np.int64).reshape(-1, 3)
    if len(tris) and (tris.min() < 0 or tris.max() >= len(dq)):
        bad = int(np.argmax((tris < 0).any(axis=1) | (tris >= len(dq)).any(axis=1)))
        raise GeometryError(
            f"manifold triangle {bad} {tris[bad].tolist()} indexes a candidate outside "
            f"0..{len(dq) - 1}"
        )
    n_per = _subdivisions(dq_translation(dq), tris, subdivisions, spacing)
    if max_poses is not None:
        n_max = int(n_per.max()) if len(n_per) else 0
        check_size(
            len(dq_in) + lattice_size(n_per) - 3 * len(n_per),
            max_poses,
            f"densify: {len(dq_in):,} candidates and {len(n_per):,} triangles with up to "
            f"{n_max:,} subdivisions give up to this many poses",
            "densify.max_poses",
            "lower densify.subdivisions (or raise densify.spacing), or ",
        )
    tri, ijk, n = _points(tris, n_per)
    weights = ijk / n[:, None].astype(np.float64)
    vertices = tris[tri]
    corners = dq[vertices]
    if method == "dlb":
        new = dlb(corners, weights, check=False)
    else:
        new = dib(corners, weights, check=False)

    n_c, m = len(dq_in), len(tri)
    cols: dict[str, Any] = {
        "dq": np.concatenate((dq_in, new.astype(dq_in.dtype))),
        "origin": np.concatenate(
            (np.full(n_c, "candidate", dtype="<U12"), np.full(m, "interpolated", dtype="<U12"))
        ),
        "triangle": np.concatenate((np.full(n_c, -1, dtype=np.int64), tri)),
        "vertices": np.concatenate((np.full((n_c, 3), -1, dtype=np.int64), vertices)),
        "weights": np.concatenate((np.full((n_c, 3), np.nan), weights)),
    }
    for name in grasps.columns:
        if name not in _OWN_COLUMNS:
            col = grasps[name]
            fill = fill_column(col, m, candidate_fill(name), vertices, weights)
            cols[name] = np.concatenate((col, fill))
    ordered = {k: cols[k] for k in (*_OWN_COLUMNS, *[c for c in cols if c not in _OWN_COLUMNS])}
    return GraspTable(ordered)
