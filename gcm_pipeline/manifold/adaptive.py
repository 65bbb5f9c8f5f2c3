r"""Adaptive densification: refine the manifold where reachability or the metric changes.

A uniform lattice (:mod:`gcm_pipeline.manifold.densify`) spends most IK solves
inside regions that are wholly reachable or wholly unreachable. Here the
triangles are refined only where something happens:

1. level 0: the candidate triangles; their vertices (every candidate) are
   checked;
2. a (sub-)triangle of level ``l < max_level`` is split into four (its edge
   midpoints) when

   * ``boundary``: its corners disagree on reachability, or
   * ``metric``: its corners are all reachable and their ranking metric
     differs by more than ``metric_threshold`` times the metric's range over
     the reachable grasps found so far, or
   * ``l < min_level`` (refine everywhere first);

3. the new midpoints are checked (IK warm-started from the solutions of the
   edge's ends and the third corner), and triangles that were not split but
   now have a checked midpoint on an edge whose reachability differs from
   their corners' are split too (repeated until nothing changes), so a
   boundary found by a neighbour is followed;
4. the children form level ``l + 1``; stop at ``max_level``.

Every point of level ``l`` is a point of the uniform lattice with
``subdivisions: 2**max_level``: weights ``ijk / 2**max_level`` of its root
triangle (exactly, in floating point), blended by the same method, so the
adaptive table is a subset of that lattice's rows. Rows carry their
``level`` (0 for the candidates, ``l`` for a point first made at level ``l``).

Points shared by neighbouring triangles are created once: a point is keyed
by its candidate (a vertex), its edge and position along it (an edge point),
or its triangle and weights (an interior point); integers only.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any

import numpy as np

from gcm_pipeline.bounds import MAX_ADAPTIVE_LEVEL, check_size
from gcm_pipeline.errors import GeometryError, InputError, choice_error
from gcm_pipeline.manifold.build import Manifold, candidate_poses
from gcm_pipeline.manifold.densify import fill_column
from gcm_pipeline.manifold.surface import blend
from gcm_pipeline.table import GraspTable, candidate_fill

__all__ = ["CRITERIA", "MAX_LEVEL", "refine", "uniform_size"]

#: Refinement criteria.
CRITERIA = ("boundary", "metric")

#: Deepest level: ``2**MAX_LEVEL`` subdivisions per root edge (keys fit in 64 bits).
MAX_LEVEL = MAX_ADAPTIVE_LEVEL

_OWN = ("dq", "origin", "triangle", "vertices", "weights", "level")
_KIND = 60  # bit of the key holding its kind (vertex, edge, interior)

#: Checks poses (M, 8) with warm starts (M, K, nq) or None; returns the
#: reachability columns (``reachable``, ``q``, ...) for the M poses.
Check = Callable[[np.ndarray, np.ndarray | None], GraspTable]
#: The ranking metric of every row of a table with reachability columns.
Score = Callable[[GraspTable], np.ndarray]


def uniform_size(triangles: np.ndarray, n_candidates: int, level: int) -> int:
    """Rows of the uniform lattice with ``subdivisions: 2**level`` (candidates included).

    Shared edge points and vertices are counted once, as densify makes them.
    """
    tris = np.asarray(triangles, dtype=np.int64).reshape(-1, 3)
    n = 1 << int(level)
    edges = np.sort(np.stack((tris, np.roll(tris, -1, axis=1)), axis=2).reshape(-1, 2), axis=1)
    n_edges = len(np.unique(edges, axis=0)) if len(edges) else 0
    return int(n_candidates + n_edges * (n - 1) + len(tris) * (n - 1) * (n - 2) // 2)


def _keys(tris: np.ndarray, root: np.ndarray, ijk: np.ndarray, scale: int) -> np.ndarray:
    """Integer keys (M,) of points ``ijk`` (M, 3) (summing to ``scale``) of root triangles.

    Vertex: the candidate id. Edge: ``(lo, hi, count at hi)``. Interior:
    ``(triangle, i, j)``. The kind sits in the top bits.
    """
    corners = tris[root]  # (M, 3) candidate ids
    nz = ijk > 0
    size = nz.sum(axis=1)
    key = np.zeros(len(ijk), dtype=np.int64)
    v = size == 1
    key[v] = corners[v][np.arange(v.sum()), np.argmax(ijk[v], axis=1)]
    e = size == 2
    if e.any():
        ce, ie, ne = corners[e], ijk[e], nz[e]
        ids = ce[ne].reshape(-1, 2)
        counts = ie[ne].reshape(-1, 2)
        swap = ids[:, 0] > ids[:, 1]
        lo = np.where(swap, ids[:, 1], ids[:, 0])
        hi = np.where(swap, ids[:, 0], ids[:, 1])
        at_hi = np.where(swap, counts[:, 0], counts[:, 1])
        key[e] = (1 << _KIND) | (lo << 31) | (hi << 11) | at_hi
    i = size == 3
    key[i] = (2 << _KIND) | (root[i] << 22) | (ijk[i, 1] << 11) | ijk[i, 2]
    return key


class _Registry:
    """Sorted point keys -> table rows."""

    def __init__(self) -> None:
        self.keys = np.zeros(0, dtype=np.int64)
        self.rows = np.zeros(0, dtype=np.int64)

    def find(self, keys: np.ndarray) -> np.ndarray:
        """Rows of ``keys`` (-1 where unknown)."""
        pos = np.searchsorted(self.keys, keys)
        pos = np.minimum(pos, max(len(self.keys) - 1, 0))
        hit = len(self.keys) > 0
        found = hit & (self.keys[pos] == keys) if hit else np.zeros(len(keys), bool)
        return np.where(found, self.rows[pos] if hit else -1, -1)

    def add(self, keys: np.ndarray, rows: np.ndarray) -> None:
        k = np.concatenate((self.keys, keys))
        r = np.concatenate((self.rows, rows))
        order = np.argsort(k, kind="stable")
        self.keys, self.rows = k[order], r[order]


def _check_options(
    max_level: int,
    min_level: int,
    criteria: Sequence[str],
    score: Score | None,
    metric_threshold: float,
) -> None:
    """Raise on a bad level, criterion or threshold of :func:`refine`."""
    if isinstance(max_level, bool) or int(max_level) != max_level:
        raise GeometryError(f"adaptive max_level must be an integer, got {max_level!r}")
    if not 1 <= max_level <= MAX_LEVEL:
        raise GeometryError(f"adaptive max_level must be in 1..{MAX_LEVEL}, got {max_level}")
    if not 0 <= min_level <= max_level:
        raise GeometryError(f"adaptive min_level must be in 0..{max_level}, got {min_level}")
    for c in criteria:
        if c not in CRITERIA:
            raise choice_error(GeometryError, "refinement criterion", c, CRITERIA)
    if not 0 < metric_threshold <= 1 or not np.isfinite(metric_threshold):
        raise GeometryError(f"metric_threshold must be in (0, 1], got {metric_threshold!r}")
    if "metric" in criteria and score is None:
        raise InputError("refinement by 'metric' needs a score function")


def _split(
    state: _State,
    rows3: np.ndarray,
    everywhere: bool,
    criteria: Sequence[str],
    score: Score | None,
    metric_threshold: float,
) -> np.ndarray:
    """Which sub-triangles (corner rows ``rows3`` (S, 3)) a level splits, by the criteria."""
    split = np.zeros(len(rows3), dtype=bool)
    if everywhere:
        split[:] = True
    reach = state.reachable[rows3]
    if "boundary" in criteria:
        split |= reach.any(axis=1) & ~reach.all(axis=1)
    if "metric" in criteria:
        assert score is not None
        values = score(state.table())
        ok = np.isfinite(values) & state.reachable
        span = float(np.ptp(values[ok])) if ok.any() else 0.0
        v3 = values[rows3]
        spread = np.where(reach.all(axis=1), np.ptp(v3, axis=1), 0.0)
        split |= np.nan_to_num(spread) > metric_threshold * span
    return split


def _subdivide(ijk: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Edge midpoints and children of sub-triangles with corners ``ijk`` (M, 3, 3).

    Returns:
        ``(mids (3M, 3), kids (4M, 3, 3))``: the midpoints of the edges ab,
        then bc, then ca; the children at a, at b, at c, then the middle one.
    """
    a, b, c = ijk[:, 0], ijk[:, 1], ijk[:, 2]
    ab, bc, ca = (a + b) // 2, (b + c) // 2, (c + a) // 2
    mids = np.concatenate((ab, bc, ca))
    kids = np.concatenate(
        (
            np.stack((a, ab, ca), axis=1),
            np.stack((ab, b, bc), axis=1),
            np.stack((ca, bc, c), axis=1),
            np.stack((ab, bc, ca), axis=1),
        )
    )
    return mids, kids


def _closure(
    state: _State,
    sub_root: np.ndarray,
    sub_ijk: np.ndarray,
    rows3: np.ndarray,
    done: np.ndarray,
    corner_rows: Callable[[np.ndarray, np.ndarray], np.ndarray],
) -> np.ndarray:
    """Sub-triangles not split yet (``~done``) with a checked midpoint of another class."""
    rest = np.flatnonzero(~done)
    if not rest.size:
        return rest
    ijk_r = sub_ijk[rest]
    mids_r = np.stack(
        (
            (ijk_r[:, 0] + ijk_r[:, 1]) // 2,
            (ijk_r[:, 1] + ijk_r[:, 2]) // 2,
            (ijk_r[:, 2] + ijk_r[:, 0]) // 2,
        ),
        axis=1,
    )
    mid_rows = corner_rows(sub_root[rest], mids_r)
    corner_class = state.reachable[rows3[rest, 0]]
    known = mid_rows >= 0
    differs = known & (state.reachable[np.maximum(mid_rows, 0)] != corner_class[:, None])
    return rest[differs.any(axis=1)]


# Over 100 lines with its docstring: the level loop shares the registry of rows and the
# checked table through two closures (corner_rows, make_points).
def refine(
    candidates: GraspTable,
    manifold: Manifold | Any,
    check: Check,
    *,
    max_level: int,
    min_level: int = 0,
    criteria: Sequence[str] = CRITERIA,
    score: Score | None = None,
    metric_threshold: float = 0.1,
    method: str = "dlb",
    max_poses: int | None = None,
) -> GraspTable:
    """Densify and check the manifold adaptively (see the module docstring).

    Args:
        candidates: The candidate table (``dq``); the manifold indexes its rows.
        manifold: Anything with ``triangles`` (T, 3).
        check: Checks poses with warm starts (see :data:`Check`), e.g.
            :class:`gcm_pipeline.pipeline.ReachabilityCheck`.
        max_level: Deepest level, 1 .. :data:`MAX_LEVEL`.
        min_level: Levels refined everywhere first (0 .. ``max_level``).
        criteria: Any of ``boundary`` and ``metric``.
        score: The ranking metric of a checked table (needed for ``metric``).
        metric_threshold: Split when the corners' metric spread exceeds this
            fraction of the metric's range over the reachable grasps so far.
        method: The blend, ``dlb`` or ``dib``.
        max_poses: Ceiling of the table's rows (``densify.max_poses``);
            checked before each level is built.

    Returns:
        The table: the candidates first (input order), then the interpolated
        rows by level; ``dq, origin, triangle, vertices, weights, level``,
        the candidates' other columns (filled as densify fills them) and the
        columns ``check`` returns.

    Raises:
        GeometryError: A bad level, criterion, threshold or method, or
            triangles indexing rows that do not exist.
        ConfigError: The table would grow beyond ``max_poses``.
    """
    _check_options(max_level, min_level, criteria, score, metric_threshold)
    dq = candidate_poses(candidates)
    tris = np.asarray(manifold.triangles, dtype=np.int64).reshape(-1, 3)
    if len(tris) and (tris.min() < 0 or tris.max() >= len(dq)):
        raise GeometryError(f"manifold triangles index candidates outside 0..{len(dq) - 1}")
    scale = 1 << int(max_level)
    n_c = len(dq)
    if n_c >= 1 << 20 or len(tris) >= 1 << 21:
        raise GeometryError(
            f"adaptive densify handles < 2**20 candidates and < 2**21 triangles, got "
            f"{n_c} and {len(tris)}"
        )
    limit = max_poses if max_poses is not None else np.iinfo(np.int64).max

    # the table grows by blocks of rows: candidates, then each batch of midpoints
    blocks: list[dict[str, np.ndarray]] = []
    checked: list[GraspTable] = []
    registry = _Registry()
    registry.add(np.arange(n_c, dtype=np.int64), np.arange(n_c, dtype=np.int64))
    blocks.append(
        {
            "triangle": np.full(n_c, -1, dtype=np.int64),
            "vertices": np.full((n_c, 3), -1, dtype=np.int64),
            "weights": np.full((n_c, 3), np.nan),
            "level": np.zeros(n_c, dtype=np.int64),
        }
    )
    checked.append(check(np.asarray(candidates["dq"], dtype=np.float64), None))
    state = _State(checked)

    # level-0 sub-triangles: the candidate triangles
    sub_root = np.arange(len(tris), dtype=np.int64)
    sub_ijk = np.broadcast_to(np.eye(3, dtype=np.int64) * scale, (len(tris), 3, 3)).copy()

    def corner_rows(root: np.ndarray, ijk: np.ndarray) -> np.ndarray:
        keys = _keys(tris, np.repeat(root, 3), ijk.reshape(-1, 3), scale)
        return registry.find(keys).reshape(-1, 3)

    def make_points(root: np.ndarray, ijk: np.ndarray, seed_rows: np.ndarray, level: int) -> None:
        """Register, blend and check the new points among ``ijk`` (M, 3) of ``root`` (M,)."""
        keys = _keys(tris, root, ijk, scale)
        unique, first = np.unique(keys, return_index=True)
        new = registry.find(unique) < 0
        if not new.any():
            return
        idx = first[new]
        n_rows = state.n_rows
        check_size(
            n_rows + int(new.sum()),
            limit,
            f"adaptive densify (level {level})",
            "densify.max_poses",
            "lower densify.adaptive.max_level or ",
        )
        r, w = root[idx], ijk[idx] / float(scale)
        poses = blend(dq[tris[r]], w, method)
        rows = np.arange(n_rows, n_rows + len(idx), dtype=np.int64)
        registry.add(unique[new], rows)
        seeds = state.q[seed_rows[idx]]  # (M, K, nq), NaN rows ignored
        blocks.append(
            {
                "triangle": r,
                "vertices": tris[r],
                "weights": w,
                "level": np.full(len(idx), level, dtype=np.int64),
            }
        )
        state.append(check(poses, seeds))

    for level in range(int(max_level)):
        if not len(sub_root):
            break
        rows3 = corner_rows(sub_root, sub_ijk)
        split = _split(state, rows3, level < min_level, criteria, score, metric_threshold)
        pending = np.flatnonzero(split)
        done = np.zeros(len(sub_root), dtype=bool)
        child_root, child_ijk = [], []
        while pending.size:
            done[pending] = True
            root = sub_root[pending]
            mids, kids = _subdivide(sub_ijk[pending])
            # midpoints, seeded from the edge's ends, then the third corner
            r3 = rows3[pending]
            seeds = np.concatenate(
                (r3[:, [0, 1, 2]], r3[:, [1, 2, 0]], r3[:, [2, 0, 1]])
            )  # ends first
            make_points(np.tile(root, 3), mids, seeds, level + 1)
            child_root.append(np.tile(root, 4))
            child_ijk.append(kids)
            # closure: unsplit triangles with a checked midpoint of another class
            if "boundary" not in criteria:
                break
            pending = _closure(state, sub_root, sub_ijk, rows3, done, corner_rows)
        if child_root:
            sub_root = np.concatenate(child_root)
            sub_ijk = np.concatenate(child_ijk)
        else:
            sub_root = sub_root[:0]
            sub_ijk = sub_ijk[:0]

    return _assemble(candidates, blocks, state)


class _State:
    """The checked rows so far: reachability columns by block, cached arrays."""

    def __init__(self, checked: list[GraspTable]) -> None:
        self.checked = checked
        self._refresh()

    def append(self, table: GraspTable) -> None:
        self.checked.append(table)
        self._refresh()

    def _refresh(self) -> None:
        self.reachable = np.concatenate(
            [np.asarray(t["reachable"], dtype=bool) for t in self.checked]
        )
        self.q = np.concatenate([np.asarray(t["q"], dtype=np.float64) for t in self.checked])
        self.n_rows = len(self.reachable)

    def table(self) -> GraspTable:
        cols = self.checked[0].columns
        return GraspTable({c: np.concatenate([t[c] for t in self.checked]) for c in cols})


def _assemble(
    candidates: GraspTable, blocks: list[dict[str, np.ndarray]], state: _State
) -> GraspTable:
    n_c = len(candidates)
    own = {k: np.concatenate([b[k] for b in blocks]) for k in blocks[0]}
    n = len(own["level"])
    m = n - n_c
    checked = state.table()
    origin = np.concatenate(
        (np.full(n_c, "candidate", dtype="<U12"), np.full(m, "interpolated", dtype="<U12"))
    )
    cols: dict[str, Any] = {
        "dq": np.asarray(checked["dq"]),
        "origin": origin,
        "triangle": own["triangle"],
        "vertices": own["vertices"],
        "weights": own["weights"],
        "level": own["level"],
    }
    verts, w = own["vertices"][n_c:], own["weights"][n_c:]
    for name in candidates.columns:
        if name in _OWN:
            continue
        col = np.asarray(candidates[name])
        cols[name] = np.concatenate((col, fill_column(col, m, candidate_fill(name), verts, w)))
    for name in checked.columns:
        if name != "dq":
            cols[name] = checked[name]
    return GraspTable(cols)
