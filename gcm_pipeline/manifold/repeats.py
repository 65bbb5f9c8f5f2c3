r"""Repeated grasps: rows of a grasp set that are one pose, exactly or nearly.

Grasp files repeat poses: a synthesiser emits the same grasp twice, files are
concatenated, or the same grasps come back after a round trip through
float32 or a text format with fewer digits. The manifold stage treats such
rows as **one pose**: the structure is built over the first row of each pose
and every other row is a repeat of it (``duplicate`` in the ``families``
structure, in no triangle in either structure; each row is still checked and
answered in the run's table).

Two rows are one pose when

* they are equal value for value, or one is the other with the quaternion
  negated (``q`` and ``-q``): **exact repeats** (:func:`first_rows`), or
* they are at most :data:`NEAR_REPEAT` (1e-5 m) apart in the pose metric
  (:mod:`gcm_pipeline.geometry.pose_metric`; 1e-5 rad of turn counts as
  1e-6 m at the default ``L``): **near repeats** (:func:`same_pose_rows`).

:data:`NEAR_REPEAT` is a tenth of the IK's default tolerances (1e-4 m, and
1e-3 rad, which counts as 1e-4 m in the metric) and about 3,000 times under
the bounds the ``families`` structure derives on ACRONYM's mug (0.031 m): an
IK solution of one row is a solution of the other, and no triangle could
join them. It is above what float32 (about 3e-8 m on a pose 1 m from the
origin) or six significant digits (about 1e-6 m) change.

Near repeats are found in O(N log N), without a neighbour search among the
copies of one pose (thousands of copies of a pose at ~the same place made the
k-d tree searches quadratic) and without a k-d tree query per row (5-10 us a
row in 7 dimensions):

1. Rows sharing a cell of a grid of side :data:`NEAR_REPEAT` ``/ (2 sqrt 7)``
   over the pose features ``[p, 2 L r]`` (``r_w >= 0``) are within
   ``NEAR_REPEAT / 2`` of each other: each is a repeat of the cell's first row.
2. Of the cells' first rows, those that may have another within
   :data:`NEAR_REPEAT` are picked out by shifted grids (none is missed:
   ``_crowded``); in a file without near repeats there are none and the
   search ends here.
3. Those rows, in row order: a row not yet a repeat keeps its pose; the rows
   within :data:`NEAR_REPEAT` of it (a k-d tree, both quaternion signs where
   ``r_w`` is small enough for the sign to matter) that are not yet repeats
   become repeats of it.

So a kept row is the first row of its pose, kept rows are more than
:data:`NEAR_REPEAT` apart, and a repeat lies within 1.5 :data:`NEAR_REPEAT`
of its kept row. A set with no two rows within :data:`NEAR_REPEAT` (no cell
holds two rows) is left as it is. A million rows take about a second.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from gcm_pipeline.geometry.pose_metric import other_sign_features, pose_features

__all__ = ["NEAR_REPEAT", "first_rows", "same_pose_rows"]

#: [m] pose-metric distance within which two grasp rows are one pose (module docstring).
NEAR_REPEAT = 1e-5
_CELL = NEAR_REPEAT / (2.0 * np.sqrt(7.0))  # grid side: a cell's diagonal is NEAR_REPEAT / 2
_CHUNK = 1 << 15  # points per k-d tree query call (a signal waits for at most one)


def first_rows(dq: np.ndarray) -> np.ndarray:
    """(N,) the first row with exactly the pose of each row (the row itself when none before).

    Rows are one pose when they are equal value for value, or one is the other
    negated (``q`` and ``-q``); for nearly equal rows see :func:`same_pose_rows`.
    """
    n = len(dq)
    lead = dq[np.arange(n), np.argmax(dq[:, :4] != 0.0, axis=1)]  # first non-zero of r
    canon = np.where(lead[:, None] < 0.0, -dq, dq) + 0.0  # + 0.0: -0.0 is 0.0
    # finite values, one zero: equal bytes are equal values
    return _first_equal(np.ascontiguousarray(canon, dtype=np.float64).view(np.uint64))


def _first_equal(keys: np.ndarray) -> np.ndarray:
    """(N,) the first row equal to each row of ``keys`` (N, K) uint64 (itself when none before).

    Rows are grouped by a 64-bit hash (a stable sort of N integers: 0.1 s for a million
    rows, where a sort of the rows' bytes takes 1 s in one call a signal waits for); a
    hash shared by unequal rows falls back to sorting the rows themselves.
    """
    n = len(keys)
    h = _hash(np.ascontiguousarray(keys.T))
    order = np.argsort(h, kind="stable")
    hs = h[order]
    start = np.flatnonzero(np.concatenate(([True], hs[1:] != hs[:-1])))
    rep = np.empty(n, dtype=np.int64)
    rep[order] = order[np.repeat(start, np.diff(np.append(start, n)))]
    if (keys == keys[rep]).all():
        return rep
    void = np.ascontiguousarray(keys).view(np.dtype((np.void, 8 * keys.shape[1]))).reshape(-1)
    _, first, inverse = np.unique(void, return_index=True, return_inverse=True)
    return first[inverse.reshape(-1)].astype(np.int64)


def same_pose_rows(dq: np.ndarray, orientation_scale: float) -> np.ndarray:
    """(N,) the kept row of each row's pose, exact and near repeats (module docstring).

    Args:
        dq: (N, 8) unit dual quaternions (finite).
        orientation_scale: ``L`` [m/rad] of the pose metric.

    Returns:
        ``rep`` (N,): ``rep[i] <= i`` is the first row of row ``i``'s pose;
        ``rep[i] == i`` for the rows kept. Without near repeats it is
        :func:`first_rows`.
    """
    rep = first_rows(dq)
    first = np.flatnonzero(rep == np.arange(len(dq)))
    if len(first) < 2:
        return rep
    feats = pose_features(dq[first], orientation_scale)
    cell = _cell_firsts(feats)  # (U,) index into first of each row's cell's first row
    reps = np.flatnonzero(cell == np.arange(len(first)))
    lead = np.arange(len(reps))  # (R,) index into reps of each cell's kept row
    crowded = np.flatnonzero(_crowded(feats[reps]))  # every pair within reach is in here
    if len(crowded):
        lead[crowded] = crowded[_leaders(feats[reps[crowded]])]
    if len(reps) == len(first) and np.array_equal(lead, np.arange(len(reps))):
        return rep  # no near repeats
    # a cell's row -> the cell's first row -> its kept row; reps ascending, so searchsorted
    kept = first[reps[lead[np.searchsorted(reps, cell)]]]
    return kept[np.searchsorted(first, rep)]


def _cell_firsts(feats: np.ndarray) -> np.ndarray:
    """(U,) the first row sharing each row's grid cell (side :data:`_CELL`)."""
    return _first_equal(_cells(feats / _CELL))


def _cells(scaled: np.ndarray) -> np.ndarray:
    """(R, 7) uint64 grid cells of coordinates in cell units; beyond int64 (1e12 m): one each."""
    scaled = np.floor(scaled)
    far = ~(np.abs(scaled) < 2.0**60).all(axis=1)
    key = np.where(far[:, None], 0.0, scaled).astype(np.int64)
    key[far, 0] = 2**62
    key[far, 1] = np.flatnonzero(far)
    return key.view(np.uint64)


def _crowded(feats: np.ndarray) -> np.ndarray:
    """(R,) whether a row may have another within :data:`NEAR_REPEAT` (none missed).

    Two rows within reach share a cell of one of ``d + 1`` grids of side a little over
    ``(d + 1) NEAR_REPEAT`` in ``d`` of the coordinates, shifted by ``1 / (d + 1)`` of
    a side along every axis: in each coordinate they are less than that shift apart,
    so each coordinate parts them in at most one grid and one grid is left. The
    positions (4 grids) sort out most rows cheaply, the 7 features (8 grids) the
    rest. Also in: rows with ``2 L |r_w| <= NEAR_REPEAT`` (maybe within reach of
    another's other sign) and rows 1e6 m out or more.
    """
    cols = np.ascontiguousarray(feats.T)  # (7, R): a coordinate's values side by side
    out = (cols[3] <= NEAR_REPEAT) | (np.abs(cols).max(axis=0) >= 1e6)
    maybe = np.flatnonzero(_share_cells(cols[:3]))
    if len(maybe):
        out[maybe] |= _share_cells(np.ascontiguousarray(cols[:, maybe]))
    return out


def _share_cells(cols: np.ndarray) -> np.ndarray:
    """(M,) whether a row shares a cell with another in one of the shifted grids (``_crowded``).

    ``cols`` (D, M); cells are told apart by a hash (a hash shared by two cells only
    adds rows).
    """
    grids = len(cols) + 1
    side = 1.01 * grids * NEAR_REPEAT
    out = np.zeros(cols.shape[1], dtype=bool)
    for shift in range(grids):
        cells = np.floor(cols / side + shift / grids) + 0.0  # + 0.0: -0.0 is 0.0
        h = _hash(cells.view(np.uint64))
        order = np.argsort(h)
        same = np.flatnonzero(h[order[1:]] == h[order[:-1]])
        out[order[same]] = True
        out[order[same + 1]] = True
    return out


def _hash(cols: np.ndarray) -> np.ndarray:
    """(N,) uint64 FNV-1a-like hash of the columns of ``cols`` (K, N) uint64 (arithmetic wraps)."""
    h = np.full(cols.shape[1], 0xCBF29CE484222325, dtype=np.uint64)
    for col in cols:
        h = (h ^ col) * np.uint64(0x100000001B3)
        h ^= h >> np.uint64(31)
    return h


def _leaders(feats: np.ndarray) -> np.ndarray:
    """(R,) the kept row of each row, greedily in row order (step 3 of the module docstring).

    Rows share no cell of :func:`_cell_firsts`' grid, so a ball holds few (a pose's
    copies fell into a few cells).
    """
    r = len(feats)
    if r < 2:
        return np.arange(r)
    # the other sign of r only where it can come within reach: 2 L |r_w| <= NEAR_REPEAT
    turn = np.flatnonzero(feats[:, 3] <= NEAR_REPEAT)
    flipped = other_sign_features(feats[turn])
    ids = np.concatenate((np.arange(r), turn))
    tree = cKDTree(np.concatenate((feats, flipped)))
    near = np.zeros(r, dtype=bool)
    k = min(3, len(ids))  # the row, its own flip, one more: one other if any is in reach
    reach = np.nextafter(NEAR_REPEAT, np.inf)  # query's bound is strict: d <= NEAR_REPEAT
    for lo in range(0, r, _CHUNK):
        dist, at = tree.query(feats[lo : lo + _CHUNK], k=k, distance_upper_bound=reach)
        found = np.isfinite(dist) & (dist <= NEAR_REPEAT)
        other = ids[np.minimum(at, len(ids) - 1)] != np.arange(lo, lo + len(dist))[:, None]
        near[lo : lo + len(dist)] = (found & other).any(axis=1)
    lead = np.arange(r)
    done = np.zeros(r, dtype=bool)
    for i in np.flatnonzero(near):
        if done[i]:
            continue
        hits = ids[np.asarray(tree.query_ball_point(feats[i], NEAR_REPEAT), dtype=np.int64)]
        hits = hits[~done[hits]]
        lead[hits] = i
        done[hits] = True
    return lead
