r"""Robustness margin: how far a reachable grasp can drift on the manifold and stay reachable.

``margin`` (N,) [m] is the distance *along the manifold* from each reachable
grasp to the nearest unreachable point: the shortest path over the row mesh
(:mod:`gcm_pipeline.manifold.lattice`), each edge as long as the pose-metric
distance between its rows,

.. math:: d^2 = \lVert \Delta p \rVert^2 + (2L)^2 \lVert \Delta r \rVert^2,

position [m] plus orientation at ``L`` = ``manifold.orientation_scale``
(0.1 m per radian by default; see :mod:`gcm_pipeline.geometry.pose_metric`).
The boundary between a reachable row and an unreachable neighbour is placed
at the middle of their edge, so a reachable row next to an unreachable one
has a margin of half that edge (the resolution of the lattice) and the
margin is 0 at the boundary and on every unreachable row. A reachable grasp
with no unreachable point anywhere on its part of the manifold has margin
``inf``. The manifold's own outer border is not a boundary: the margin
measures reachability, not the extent of the candidate set.

A row on no edge of the mesh (a candidate that no triangle uses: an
isolated point of the manifold) has margin 0 even when reachable: the
manifold around it is the point itself, so no drift along it is known to
stay reachable. (``inf`` would rank such a row, about whose neighbourhood
the run knows nothing, above every row with a measured margin.)
"""

from __future__ import annotations

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import dijkstra

from gcm_pipeline.geometry.pose_metric import ORIENTATION_SCALE, pose_distance

__all__ = ["margin"]


def margin(
    dq: np.ndarray,
    reachable: np.ndarray,
    edges: np.ndarray,
    orientation_scale: float = ORIENTATION_SCALE,
) -> np.ndarray:
    """Distance [m] along the manifold from each row to the nearest unreachable point.

    Args:
        dq: (N, 8) poses of the rows (world).
        reachable: (N,) bool.
        edges: (E, 2) neighbour rows (:attr:`~gcm_pipeline.manifold.lattice.RowMesh.edges`).
        orientation_scale: ``L`` [m/rad] of the pose metric.

    Returns:
        (N,) margins: 0 for unreachable rows and for rows on no edge
        (isolated), ``inf`` where no unreachable point can be reached along
        the mesh.
    """
    reach = np.asarray(reachable, dtype=bool)
    n = len(reach)
    e = np.asarray(edges, dtype=np.int64).reshape(-1, 2)
    linked = np.zeros(n, dtype=bool)
    linked[e.ravel()] = True
    out = np.where(reach & linked, np.inf, 0.0)
    if not len(e) or reach.all() or not reach.any():
        return out
    length = pose_distance(dq[e[:, 0]], dq[e[:, 1]], orientation_scale)
    ra, rb = reach[e[:, 0]], reach[e[:, 1]]
    inner = ra & rb
    border = ra ^ rb
    # node n is the boundary: joined to each reachable row at half its border edges
    inside_all = np.where(ra[border], e[border, 0], e[border, 1])
    half_all = np.full(n, np.inf)
    np.minimum.at(half_all, inside_all, 0.5 * length[border])  # one entry per row: the nearest
    inside = np.unique(inside_all)
    half = half_all[inside]
    rows = np.concatenate((e[inner, 0], e[inner, 1], np.full(len(inside), n), inside))
    cols = np.concatenate((e[inner, 1], e[inner, 0], inside, np.full(len(inside), n)))
    weight = np.concatenate((length[inner], length[inner], half, half))
    # a zero-length edge must still count as an edge (sparse graphs drop explicit zeros)
    weight = np.maximum(weight, 1e-300)
    graph = coo_matrix((weight, (rows, cols)), shape=(n + 1, n + 1)).tocsr()
    dist = dijkstra(graph, directed=False, indices=n)
    inner_rows = reach & linked
    out[inner_rows] = dist[:n][inner_rows]
    return out
