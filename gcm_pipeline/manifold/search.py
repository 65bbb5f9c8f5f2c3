"""The searches of the grasp manifold's queries, on plain arrays.

:func:`search_near_rows` is the second step of
``GraspManifold.nearest_reachable`` (project onto the triangles of the nearest
reachable rows, bisect towards the unreachable projections);
:func:`pattern_search` is the climb of ``GraspManifold.best``. Both take the
manifold as a :class:`Surface` (its poses, triangles and blend) and the
reachability check as a callable.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import NamedTuple, Protocol

import numpy as np

from gcm_pipeline.geometry.pose_metric import pose_distance
from gcm_pipeline.manifold.build import Manifold
from gcm_pipeline.manifold.lattice import row_memberships
from gcm_pipeline.manifold.surface import blend, project_onto_triangles
from gcm_pipeline.table import GraspTable

__all__ = [
    "Answers",
    "BestGrasps",
    "NearestReachable",
    "Surface",
    "first_unique",
    "pattern_search",
    "search_near_rows",
]


class NearestReachable(NamedTuple):
    """The nearest reachable grasps of M query poses.

    Attributes:
        dq: (M, 8) the grasp (world), on the manifold; NaN where none was found.
        q: (M, nq) its IK solution [rad], verified by Pinocchio FK, collision
            free and approachable as in the run.
        distance: (M,) pose-metric distance [m] from the query to the grasp.
        triangle: (M,) manifold triangle of the grasp; -1 if none was found
            or the grasp is an isolated candidate (see ``vertex``).
        weights: (M, 3) its barycentric weights there (``(1, 0, 0)`` at an
            isolated candidate, NaN if none was found).
        found: (M,) bool, False when no reachable grasp was found near the query.
        located: (M,) distance [m] from the query to the manifold itself
            (``GraspManifold.locate``); equal to ``distance`` when the
            nearest manifold point is reachable.
        vertex: (M,) table row of the grasp when it is a candidate in no
            triangle (an isolated point of the manifold), else -1.
    """

    dq: np.ndarray
    q: np.ndarray
    distance: np.ndarray
    triangle: np.ndarray
    weights: np.ndarray
    found: np.ndarray
    located: np.ndarray
    vertex: np.ndarray


class Answers:
    """The nearest reachable grasp offered so far for each of M queries.

    Args:
        query: (M, 8) the query poses.
        nq: Joints of the robot.
        orientation_scale: ``L`` [m/rad] of the pose metric.
    """

    def __init__(self, query: np.ndarray, nq: int, orientation_scale: float) -> None:
        m = len(query)
        self.query = query
        self.orientation_scale = orientation_scale
        self.dq = np.full((m, 8), np.nan)
        self.q = np.full((m, nq), np.nan)
        self.distance = np.full(m, np.inf)
        self.triangle = np.full(m, -1, dtype=np.int64)
        self.weights = np.full((m, 3), np.nan)
        self.vertex = np.full(m, -1, dtype=np.int64)

    def offer(
        self,
        i: np.ndarray,
        dq: np.ndarray,
        q: np.ndarray,
        t: np.ndarray,
        w: np.ndarray,
        v: np.ndarray,
    ) -> None:
        """Offer reachable grasps to queries ``i``; each query keeps the nearest.

        ``dq`` the grasps, ``q`` their solutions, ``t`` their triangles, ``w``
        their weights, ``v`` their rows when isolated (else -1).
        """
        if not len(i):
            return
        d = pose_distance(dq, self.query[i], self.orientation_scale)
        # several offers for one query: keep the nearest (lexsort by distance)
        order = np.lexsort((d, i))
        i, dq, q, t, w, v, d = (a[order] for a in (i, dq, q, t, w, v, d))
        first = np.r_[True, i[1:] != i[:-1]]
        i, dq, q, t, w, v, d = (a[first] for a in (i, dq, q, t, w, v, d))
        better = d < self.distance[i]
        i = i[better]
        self.dq[i], self.q[i], self.distance[i] = dq[better], q[better], d[better]
        self.triangle[i], self.weights[i], self.vertex[i] = t[better], w[better], v[better]

    def result(self, located: np.ndarray) -> NearestReachable:
        """The answers, with the distances ``located`` to the manifold."""
        found = np.isfinite(self.distance)
        distance = np.where(found, self.distance, np.nan)
        return NearestReachable(
            self.dq, self.q, distance, self.triangle, self.weights, found, located, self.vertex
        )


class BestGrasps(NamedTuple):
    """Grasps found by ``GraspManifold.best``, best first.

    Attributes:
        dq: (K, 8) the grasps (world), points of the manifold.
        q: (K, nq) their verified IK solutions [rad].
        value: (K,) the metric at each grasp (same scale as the run's column).
        triangle: (K,) manifold triangle of each grasp; -1 for an isolated
            candidate (the grasp is then ``start_row`` itself).
        weights: (K, 3) barycentric weights there (``(1, 0, 0)`` if isolated).
        start_row: (K,) the table row each search started from.
        start_value: (K,) the metric of that row; ``value >= start_value``.
        metric: The metric's name.
    """

    dq: np.ndarray
    q: np.ndarray
    value: np.ndarray
    triangle: np.ndarray
    weights: np.ndarray
    start_row: np.ndarray
    start_value: np.ndarray
    metric: str


class Surface(Protocol):
    """What the searches read of a grasp manifold."""

    #: The triangles over the candidate rows.
    mesh: Manifold
    #: The run's grasp table (candidates first).
    grasps: GraspTable
    #: (V, 8) the vertex poses.
    poses: np.ndarray
    #: The blend, ``dlb`` or ``dib``.
    method: str
    #: ``L`` [m/rad] of the pose metric.
    orientation_scale: float

    @property
    def triangles(self) -> np.ndarray:
        """(T, 3) candidate row ids of the triangles."""
        ...


def search_near_rows(
    m: Surface,
    query: np.ndarray,
    todo: np.ndarray,
    near: np.ndarray,
    q_table: np.ndarray,
    check: Callable[..., GraspTable],
    bisections: int,
    offer: Callable[..., None],
) -> None:
    """Step 2 of ``GraspManifold.nearest_reachable`` for the queries ``todo``.

    Each near row, re-checked from its own solution, is offered itself (so
    the answer is never farther than the nearest reachable row, whether or
    not a triangle uses it). Each query is then projected onto the triangles
    around its nearest reachable rows; a reachable projection is offered, an
    unreachable one is bisected from the row towards it (``bisections``
    halvings) and the last reachable point is offered. ``offer(queries, dq,
    q, triangles, weights, isolated rows)`` keeps the nearest per query.
    """
    n_v = m.mesh.n_vertices
    mem_row, mem_tri, mem_w = row_memberships(m.grasps, m.triangles, n_v)
    order = np.argsort(mem_row, kind="stable")
    mem_row, mem_tri, mem_w = mem_row[order], mem_tri[order], mem_w[order]
    # the rows themselves, re-checked from their own solutions
    rows = np.unique(near)
    res = check(m.grasps["dq"][rows], q_table[rows][:, None, :])
    good = np.asarray(res["reachable"], dtype=bool)
    q_row = np.full((len(m.grasps), q_table.shape[1]), np.nan)
    q_row[rows[good]] = np.asarray(res["q"])[good]
    # pairs (query, membership of a near row)
    qi = np.repeat(todo, near.shape[1])
    r = near.ravel()
    keep = np.isfinite(q_row[r]).all(axis=1)
    qi, r = qi[keep], r[keep]
    lo = np.searchsorted(mem_row, r, side="left")
    hi = np.searchsorted(mem_row, r, side="right")
    counts = hi - lo
    alone = counts == 0  # rows in no triangle: isolated points of the manifold
    ra = r[alone]
    offer(
        qi[alone],
        np.asarray(m.grasps["dq"])[ra],
        q_row[ra],
        np.full(len(ra), -1, dtype=np.int64),
        np.tile([1.0, 0.0, 0.0], (len(ra), 1)),
        ra,
    )
    pair_q = np.repeat(qi, counts)
    pair_r = np.repeat(r, counts)
    pos = (
        np.concatenate([np.arange(a, b) for a, b in zip(lo, hi, strict=True)])
        if len(lo)
        else np.zeros(0, np.int64)
    )
    pair_t, pair_w0 = mem_tri[pos], mem_w[pos]
    row_dq = np.asarray(m.grasps["dq"])[pair_r]
    none = np.full(len(pair_q), -1, dtype=np.int64)
    offer(pair_q, row_dq, q_row[pair_r], pair_t, pair_w0, none)
    if not len(pair_q):
        return
    corners = m.poses[m.triangles[pair_t]]
    w_y, _ = project_onto_triangles(
        query[pair_q],
        corners,
        pair_w0[:, 1:],
        method=m.method,
        orientation_scale=m.orientation_scale,
    )
    # the projections: reachable ones are offered, the others bisected
    y = blend(corners, w_y, m.method)
    res = check(y, q_row[pair_r][:, None, :])
    ok = np.asarray(res["reachable"], dtype=bool)
    offer(pair_q[ok], y[ok], np.asarray(res["q"])[ok], pair_t[ok], w_y[ok], none[ok])
    b = np.flatnonzero(~ok)
    s_lo = np.zeros(len(b))
    s_hi = np.ones(len(b))
    q_lo = q_row[pair_r[b]]
    for _ in range(int(bisections)):
        if not len(b):
            break
        s = 0.5 * (s_lo + s_hi)
        w = (1.0 - s)[:, None] * pair_w0[b] + s[:, None] * w_y[b]
        pts = blend(corners[b], w, m.method)
        res = check(pts, q_lo[:, None, :])
        ok = np.asarray(res["reachable"], dtype=bool)
        s_lo = np.where(ok, s, s_lo)
        s_hi = np.where(ok, s_hi, s)
        q_lo[ok] = np.asarray(res["q"])[ok]
    moved = s_lo > 0
    if moved.any():
        bb = b[moved]
        w = (1.0 - s_lo[moved])[:, None] * pair_w0[bb] + s_lo[moved][:, None] * w_y[bb]
        pts = blend(corners[bb], w, m.method)
        offer(pair_q[bb], pts, q_lo[moved], pair_t[bb], w, none[bb])


def pattern_search(
    m: Surface,
    t: np.ndarray,
    w: np.ndarray,
    q_cur: np.ndarray,
    val: np.ndarray,
    dq_cur: np.ndarray,
    *,
    step: float,
    iterations: int,
    check: Callable[..., GraspTable],
    values: Callable[[GraspTable, np.ndarray, np.ndarray], np.ndarray],
    inside: Callable[[np.ndarray, np.ndarray], np.ndarray],
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Climb a metric inside triangles by a pattern search on barycentric weights.

    Six directions per search; a move is taken only to a point that is
    reachable (``check``, warm-started from the current solution), in the
    region (``inside``) and strictly better (``values``); the step halves when
    none is, and a search stops below 1/64 of its first step.

    Args:
        m: The manifold's poses, triangles and blend.
        t: (S,) triangle of each search.
        w: (S, 3) start weights.
        q_cur: (S, nq) start solutions [rad].
        val: (S,) start metric values.
        dq_cur: (S, 8) start poses.
        step: First step in barycentric weights.
        iterations: Pattern-search iterations.
        check: Reachability of poses (M, 8) with warm starts (M, 1, nq).
        values: Metric of checked points ``values(table, triangles, weights)``.
        inside: Region mask ``inside(triangles, poses)``.

    Returns:
        ``(w, q_cur, val, dq_cur)``: where each search ended (the inputs, updated in place).
    """
    step = np.full(len(t), step)
    directions = np.array(
        [[1, -1, 0], [-1, 1, 0], [0, 1, -1], [0, -1, 1], [-1, 0, 1], [1, 0, -1]], float
    )
    min_step = step / 64.0
    for _ in range(iterations):
        act = np.flatnonzero(step >= min_step)
        if not act.size:
            break
        trial_w = (w[act, None, :] + step[act, None, None] * directions[None]).reshape(-1, 3)
        owner = np.repeat(act, len(directions))
        valid = (trial_w >= -1e-12).all(axis=1)
        trial_w = np.clip(trial_w, 0.0, None)
        trial_w /= trial_w.sum(axis=1, keepdims=True)
        trial_t = t[owner]
        pts = blend(m.poses[m.triangles[trial_t]], trial_w, m.method)
        valid &= inside(trial_t, pts)
        gain = np.full(len(owner), -np.inf)
        new_q = np.full((len(owner), q_cur.shape[1]), np.nan)
        trial_vals = np.full(len(owner), np.nan)
        if valid.any():
            v = np.flatnonzero(valid)
            res = check(pts[v], q_cur[owner[v]][:, None, :])
            vals = values(res, trial_t[v], trial_w[v])
            good = np.asarray(res["reachable"], dtype=bool) & np.isfinite(vals)
            gain[v[good]] = vals[good] - val[owner[v[good]]]
            new_q[v[good]] = np.asarray(res["q"])[good]
            trial_vals[v] = vals
        gains = gain.reshape(len(act), len(directions))
        pick = np.argmax(gains, axis=1)
        best_gain = gains[np.arange(len(act)), pick]
        moved = best_gain > 0
        flat = np.arange(len(act)) * len(directions) + pick
        mv = act[moved]
        w[mv] = trial_w[flat[moved]]
        q_cur[mv] = new_q[flat[moved]]
        val[mv] = trial_vals[flat[moved]]
        dq_cur[mv] = pts[flat[moved]]
        step[act[~moved]] *= 0.5
    return w, q_cur, val, dq_cur


def first_unique(values: np.ndarray, k: int) -> np.ndarray:
    """The first ``k`` distinct entries of each row of ``values`` (M, P), in order.

    Each row must hold at least ``k`` distinct values.
    """
    earlier = np.triu(np.ones((values.shape[1],) * 2, dtype=bool), k=1)  # [a, b]: a before b
    dup = ((values[:, :, None] == values[:, None, :]) & earlier[None]).any(axis=1)
    order = np.argsort(dup, axis=1, kind="stable")[:, :k]
    return np.take_along_axis(values, order, axis=1)
