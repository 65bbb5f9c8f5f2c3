"""IK continuity across the manifold: joint jumps, IK-branch patches, re-seeding.

Neighbouring grasps of the manifold (edges of the row mesh,
:mod:`gcm_pipeline.manifold.lattice`) are close poses; a planner that moves
along the manifold needs their IK solutions close too. An elbow or wrist flip
between neighbours makes the region useless for continuous motion even when
every grasp in it is reachable.

Columns:

* ``ik_jump`` (N,) [rad]: the largest joint-space jump (L-infinity norm of
  ``q_a - q_b``) from a reachable grasp to the solutions of its reachable
  neighbours; NaN for unreachable grasps and for grasps with no reachable
  neighbour.
* ``patch`` (N,) int: connected regions of reachable grasps in which
  neighbouring solutions differ by at most ``threshold`` (one IK branch),
  numbered by decreasing size (0 = largest, ties by lowest row); -1 for
  unreachable grasps.

Re-seeding (:func:`reseed`) merges patches: a grasp at the border of a
smaller patch is re-solved from the solution of its neighbour in a larger
patch (the IK warm-started from it, collisions and approach checked as in the
run); if the new solution is valid and within ``threshold`` of that
neighbour's, it replaces the old one and the grasp joins the larger patch.
Rounds repeat until no grasp moves, so larger patches grow into smaller ones
along every path the robot's IK allows. Reachability never changes, only
which valid solution a grasp keeps.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, NamedTuple

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from gcm_pipeline.errors import InputError
from gcm_pipeline.table import GraspTable

__all__ = [
    "DEFAULT_THRESHOLD",
    "ReseedReport",
    "continuity_columns",
    "ik_jumps",
    "patches",
    "reseed",
]

#: Largest joint jump [rad] between neighbours of one patch (one IK branch).
DEFAULT_THRESHOLD = 0.5

Check = Callable[[np.ndarray, np.ndarray | None], GraspTable]


class ReseedReport(NamedTuple):
    """What :func:`reseed` did.

    Attributes:
        patches_before: Patches before re-seeding.
        patches_after: Patches after.
        moved: Grasps that took a new solution.
        rounds: Rounds run.
        solved: IK targets checked.
    """

    patches_before: int
    patches_after: int
    moved: int
    rounds: int
    solved: int


def _jumps(q: np.ndarray, edges: np.ndarray) -> np.ndarray:
    """L-infinity joint distance [rad] (E,) across each edge."""
    if not len(edges):
        return np.zeros(0)
    return np.abs(q[edges[:, 0]] - q[edges[:, 1]]).max(axis=1)


def _reachable_edges(reachable: np.ndarray, edges: np.ndarray) -> np.ndarray:
    edges = np.asarray(edges, dtype=np.int64).reshape(-1, 2)
    return edges[reachable[edges[:, 0]] & reachable[edges[:, 1]]]


def ik_jumps(q: np.ndarray, reachable: np.ndarray, edges: np.ndarray) -> np.ndarray:
    """Largest joint jump [rad] (N,) from each reachable row to its reachable neighbours.

    Args:
        q: (N, nq) IK solutions [rad] (NaN rows for unreachable grasps).
        reachable: (N,) bool.
        edges: (E, 2) neighbour row pairs.

    Returns:
        (N,) NaN for unreachable rows and rows without a reachable neighbour.
    """
    reach = np.asarray(reachable, dtype=bool)
    e = _reachable_edges(reach, edges)
    out = np.full(len(reach), -np.inf)
    j = _jumps(np.asarray(q, dtype=np.float64), e)
    np.maximum.at(out, e[:, 0], j)
    np.maximum.at(out, e[:, 1], j)
    out[~np.isfinite(out)] = np.nan
    return out


def patches(
    q: np.ndarray, reachable: np.ndarray, edges: np.ndarray, threshold: float = DEFAULT_THRESHOLD
) -> np.ndarray:
    """Patch id (N,) of every row: connected by edges whose joint jump is <= ``threshold``.

    Ids are 0, 1, ... by decreasing patch size (ties: the patch with the
    lowest row first); -1 for unreachable rows.

    Raises:
        InputError: ``threshold`` not a positive number.
    """
    if not np.isfinite(threshold) or threshold <= 0:
        raise InputError(f"continuity threshold must be a positive angle [rad], got {threshold!r}")
    reach = np.asarray(reachable, dtype=bool)
    n = len(reach)
    e = _reachable_edges(reach, edges)
    e = e[_jumps(np.asarray(q, dtype=np.float64), e) <= threshold]
    graph = coo_matrix((np.ones(len(e)), (e[:, 0], e[:, 1])), shape=(n, n))
    _, label = connected_components(graph, directed=False)
    out = np.full(n, -1, dtype=np.int64)
    rows = np.flatnonzero(reach)
    if not rows.size:
        return out
    labels, first, size = np.unique(label[rows], return_index=True, return_counts=True)
    order = np.lexsort((rows[first], -size))  # largest first, then lowest row
    rank = np.empty(len(labels), dtype=np.int64)
    rank[order] = np.arange(len(labels))
    lookup = np.full(label.max() + 1, -1, dtype=np.int64)
    lookup[labels] = rank
    out[rows] = lookup[label[rows]]
    return out


def reseed(
    grasps: GraspTable,
    edges: np.ndarray,
    check: Check,
    *,
    threshold: float = DEFAULT_THRESHOLD,
    max_rounds: int = 100,
) -> tuple[GraspTable, ReseedReport]:
    """Merge IK patches by re-solving border grasps from their larger neighbours.

    Args:
        grasps: Table with the reachability columns (``dq``, ``reachable``, ``q``, ...).
        edges: (E, 2) neighbour rows (:attr:`~gcm_pipeline.manifold.lattice.RowMesh.edges`).
        check: Checks poses warm-started from given solutions, as the run does
            (:class:`~gcm_pipeline.pipeline.ReachabilityCheck`).
        threshold: Largest joint jump [rad] within a patch.
        max_rounds: Upper bound on the rounds.

    Returns:
        The table (``q`` and the columns ``check`` returns replaced for the
        grasps that moved) and a :class:`ReseedReport`.
    """
    for col in ("dq", "reachable", "q"):
        if col not in grasps:
            raise InputError(f"re-seeding needs column {col!r}; columns: {', '.join(grasps)}")
    reach = np.asarray(grasps["reachable"], dtype=bool)
    q = np.array(grasps["q"], dtype=np.float64)
    edges = _reachable_edges(reach, edges)
    pid = patches(q, reach, edges, threshold)
    before = int(pid.max(initial=-1) + 1)
    updates: dict[str, np.ndarray] = {}
    failed: set[tuple[int, int]] = set()
    moved = solved = rounds = 0
    dq = np.asarray(grasps["dq"], dtype=np.float64)
    for rounds in range(1, int(max_rounds) + 1):  # noqa: B007 - reported
        # border edges between patches: the row of the smaller patch is the target
        a, b = edges[:, 0], edges[:, 1]
        cross = pid[a] != pid[b]
        src = np.where(pid[a] < pid[b], a, b)[cross]
        dst = np.where(pid[a] < pid[b], b, a)[cross]
        if not len(dst):
            break
        # one source per target: the largest patch, then the lowest row
        order = np.lexsort((src, pid[src], dst))
        src, dst = src[order], dst[order]
        first = np.r_[True, dst[1:] != dst[:-1]]
        src, dst = src[first], dst[first]
        fresh = np.array([(int(d), int(s)) not in failed for d, s in zip(dst, src, strict=True)])
        src, dst = src[fresh], dst[fresh]
        if not len(dst):
            break
        res = check(dq[dst], q[src][:, None, :])
        solved += len(dst)
        new_q = np.asarray(res["q"], dtype=np.float64)
        ok = np.array(res["reachable"], dtype=bool)
        ok &= np.abs(new_q - q[src]).max(axis=1) <= threshold
        for d, s in zip(dst[~ok].tolist(), src[~ok].tolist(), strict=True):
            failed.add((d, s))
        if not ok.any():
            continue
        rows = dst[ok]
        q[rows] = new_q[ok]
        for col in res.columns:
            if col in ("dq", "q"):
                continue
            if col not in updates:
                if col not in grasps:
                    continue
                updates[col] = np.array(grasps[col])
            updates[col][rows] = np.asarray(res[col])[ok]
        if "solution" in grasps:  # the re-solved answer is branch 0 of its new branches
            if "solution" not in updates:
                updates["solution"] = np.array(grasps["solution"])
            updates["solution"][rows] = 0
        moved += len(rows)
        pid = patches(q, reach, edges, threshold)
    after = int(pid.max(initial=-1) + 1)
    table = grasps.with_columns(q=q, **updates)
    return table, ReseedReport(before, after, moved, rounds, solved)


def continuity_columns(
    grasps: GraspTable, edges: np.ndarray, threshold: float = DEFAULT_THRESHOLD
) -> dict[str, Any]:
    """``ik_jump`` and ``patch`` of a table with ``reachable`` and ``q``."""
    reach = np.asarray(grasps["reachable"], dtype=bool)
    q = np.asarray(grasps["q"], dtype=np.float64)
    return {
        "ik_jump": ik_jumps(q, reach, edges),
        "patch": patches(q, reach, edges, threshold),
    }
