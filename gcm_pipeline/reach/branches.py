"""Several IK branches per grasp: choose which one each grasp takes.

With ``ik.solutions: K`` the reachability engine keeps up to K verified
solutions per reachable grasp that pass every check (collisions, approach,
retreat), in the ``solutions`` column (N, K, nq), branch 0 being the first one
found. :func:`select_branches` picks one per grasp (``ik.select``):

* ``metric``: the branch with the best ranking metric (ties: the lower branch);
* ``continuity``: branches that agree with the neighbours on the manifold.
  In every connected region of reachable grasps, the grasp with the best
  metric keeps its best branch; the others follow in breadth-first order
  (by depth from it, layer by layer), each taking the branch nearest (L-infinity
  joint distance) to the branch chosen by its predecessor; then a few sweeps
  let every grasp switch to the branch with the fewest neighbours farther than
  ``threshold`` (then the smallest sum of joint jumps to them), alternating
  between two halves of the rows so that neighbours rarely move at once. If
  that gives more patches than every grasp keeping its first branch found, the
  first branches are kept.

The chosen branch replaces ``q``, ``q_pregrasp``, ``q_retreat`` and
``clearance``; ``solution`` (N,) is its index (-1 for unreachable grasps).
"""

from __future__ import annotations

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components, dijkstra

from gcm_pipeline.errors import InputError, choice_error
from gcm_pipeline.manifold.continuity import patches
from gcm_pipeline.table import GraspTable

__all__ = ["SELECT_METHODS", "select_branches"]

SELECT_METHODS = ("continuity", "metric")

_SWEEPS = 6

#: Branch columns (N, K, ...) and the table column each one fills.
_BRANCH_COLUMNS = {
    "solutions": "q",
    "solutions_q_pregrasp": "q_pregrasp",
    "solutions_q_retreat": "q_retreat",
    "solutions_clearance": "clearance",
}


def _best_by_score(scores: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """Index (N,) of the best valid branch per row (ties: lowest); 0 where none is valid."""
    s = np.where(valid, np.nan_to_num(scores, nan=-np.inf), -np.inf)
    s = np.where(valid & ~np.isfinite(s), -1e300, s)  # a valid branch without a score
    return np.argmax(s, axis=1)


def _continuity(
    q: np.ndarray,
    valid: np.ndarray,
    edges: np.ndarray,
    first: np.ndarray,
    scores: np.ndarray,
    threshold: float,
) -> np.ndarray:
    """Branch per row chosen for continuity (see the module docstring)."""
    n = len(q)
    rows = np.flatnonzero(valid.any(axis=1))
    chosen = first.copy()
    e = edges[valid[edges[:, 0]].any(axis=1) & valid[edges[:, 1]].any(axis=1)]
    if not len(e) or not rows.size:
        return chosen
    graph = coo_matrix((np.ones(len(e)), (e[:, 0], e[:, 1])), shape=(n, n)).tocsr()
    _, label = connected_components(graph, directed=False)
    best = np.where(valid, np.nan_to_num(scores, nan=-np.inf), -np.inf).max(axis=1)
    # root of each region: its best-scored grasp (ties: lowest row)
    order = np.lexsort((rows, -best[rows], label[rows]))
    head = order[np.r_[True, label[rows][order][1:] != label[rows][order][:-1]]]
    roots = rows[head]
    depth, pred = dijkstra(
        graph,
        directed=False,
        indices=roots,
        unweighted=True,
        min_only=True,
        return_predecessors=True,
    )[:2]
    finite = np.isfinite(depth)
    levels = depth[finite].astype(np.int64)
    on = np.flatnonzero(finite)
    big = 1e9
    for d in range(1, int(levels.max(initial=0)) + 1):
        at = on[levels == d]
        at = at[valid[at].any(axis=1)]
        if not at.size:
            continue
        ref = q[pred[at], chosen[pred[at]]]  # (M, nq) the predecessor's branch
        with np.errstate(invalid="ignore"):
            dist = np.abs(q[at] - ref[:, None, :]).max(axis=2)  # NaN past the valid branches
        dist = np.where(valid[at] & np.isfinite(dist), dist, big)
        chosen[at] = np.argmin(dist, axis=1)
    # sweeps: fewest neighbours beyond the threshold, then the smallest jumps
    both = np.concatenate((e, e[:, ::-1]))
    half = rows % 2
    for sweep in range(_SWEEPS):
        q_now = q[np.arange(n), chosen]  # (N, nq)
        jump = np.abs(q[both[:, 0]] - q_now[both[:, 1]][:, None, :]).max(axis=2)  # (2E, K)
        far = np.zeros(q.shape[:2])
        total = np.zeros(q.shape[:2])
        np.add.at(far, both[:, 0], (jump > threshold).astype(float))
        np.add.at(total, both[:, 0], np.nan_to_num(jump, nan=big))
        cost = far * big + total
        cost = np.where(valid, cost, np.inf)
        pick = np.argmin(cost, axis=1)
        current = cost[np.arange(n), chosen]
        better = cost[np.arange(n), pick] < current - 1e-12
        move = rows[better[rows] & (half == sweep % 2)]
        if not move.size and sweep % 2 == 1:
            break
        chosen[move] = pick[move]
    # a heuristic: never worse than every grasp keeping the first branch found
    reach = np.asarray(valid.any(axis=1))
    count = [
        patches(q[np.arange(n), c], reach, edges, threshold).max() for c in (chosen, 0 * chosen)
    ]
    return chosen if count[0] <= count[1] else np.zeros_like(chosen)


def select_branches(
    grasps: GraspTable,
    edges: np.ndarray,
    scores: np.ndarray,
    *,
    method: str = "metric",
    threshold: float = 0.5,
) -> GraspTable:
    """Choose one IK branch per grasp (see the module docstring).

    Args:
        grasps: Table with ``solutions`` (N, K, nq) and ``n_solutions`` (N,)
            (and the other branch columns), from the reachability stage with
            several branches.
        edges: (E, 2) neighbour rows on the manifold (for ``continuity``).
        scores: (N, K) the ranking metric of each branch (higher is better;
            NaN where none).
        method: ``metric`` or ``continuity``.
        threshold: Largest joint jump [rad] between neighbours of one patch.

    Returns:
        The table with ``q``, ``q_pregrasp``, ``q_retreat``, ``clearance`` of
        the chosen branch and ``solution`` (N,) its index (-1: unreachable).

    Raises:
        InputError: Unknown method, missing branch columns, scores of the
            wrong shape.
    """
    if method not in SELECT_METHODS:
        raise choice_error(InputError, "ik.select", method, SELECT_METHODS, key="ik.select")
    for col in ("solutions", "n_solutions", "reachable"):
        if col not in grasps:
            raise InputError(f"choosing IK branches needs column {col!r} (ik.solutions > 1)")
    q = np.asarray(grasps["solutions"], dtype=np.float64)
    n, k = q.shape[:2]
    scores = np.asarray(scores, dtype=np.float64)
    if scores.shape != (n, k):
        raise InputError(f"branch scores must have shape ({n}, {k}), got {scores.shape}")
    count = np.asarray(grasps["n_solutions"], dtype=np.int64)
    reach = np.asarray(grasps["reachable"], dtype=bool)
    valid = (np.arange(k)[None, :] < count[:, None]) & reach[:, None]
    chosen = _best_by_score(scores, valid)
    if method == "continuity":
        chosen = _continuity(
            q, valid, np.asarray(edges, dtype=np.int64).reshape(-1, 2), chosen, scores, threshold
        )
    chosen = np.where(reach & (count > 0), chosen, 0)
    cols: dict[str, np.ndarray] = {}
    rows = np.arange(n)
    for src, dst in _BRANCH_COLUMNS.items():
        if src in grasps and dst in grasps:
            values = np.asarray(grasps[src])[rows, chosen]
            keep = np.array(grasps[dst])
            keep[reach] = values[reach]
            cols[dst] = keep
    cols["solution"] = np.where(reach, chosen, -1)
    return grasps.with_columns(**cols)
