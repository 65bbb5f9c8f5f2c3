r"""The ``families`` structure: triangles between grasps that are near in SE(3).

The paper's chart (:mod:`gcm_pipeline.manifold.charts`) projects the grasp
positions onto one plane; on a synthesiser's real output (many orientations
at one position, grasps from several sides, clusters) most of its triangles
then join grasps far apart in orientation and are pruned, and half the
candidates end up in no triangle. This structure links grasps by the
package's pose metric (:mod:`gcm_pipeline.geometry.pose_metric`) instead:

1. **Neighbours.** Two candidates are neighbours when their positions are at
   most ``max_edge_length`` [m] apart *and* their orientations at most
   ``max_edge_angle_deg`` (found with a KD-tree over the pose features
   ``[p, 2 L r]``, both quaternion signs, then checked exactly, a pair on a
   bound counting as within it: :data:`BOUND_TOLERANCE`).
2. **Families.** The connected components of the neighbour graph. Grasps from
   different sides of an object, or with approach/closing axes further apart
   than the bounds allow, fall into different families; no triangle ever
   joins two families.
3. **A chart per family.** The two principal axes of the family's pose
   features (sign-aligned to the family's first grasp): a local linear
   embedding in the pose metric, position and orientation together. The
   chart is triangulated (``qhull`` or the paper's ``bowyer_watson``) and a
   triangle is kept only when its three edges are neighbour pairs, i.e.
   within both bounds (pruned ones are reported as ``edge_length`` /
   ``edge_angle`` like the chart structure's).
4. **Fill.** A candidate still in no triangle but *linkable* (two of its
   neighbours are neighbours of each other) gets the triangle with it and
   two such neighbours whose longest pose-metric edge is shortest. So every
   linkable candidate is in a triangle and every triangle is within the
   bounds. Filled triangles may overlap chart triangles (the structure is a
   set of triangles, not a surface without overlaps).

Each candidate gets its ``family`` (-1 for one whose pose duplicates an
earlier row) and why it is in no triangle (``isolation``): ``""`` linked,
``no_neighbour`` (no other grasp within the bounds), ``no_triple`` (no two of
its neighbours are neighbours of each other) or ``duplicate`` (the same pose
as an earlier row: an exact repeat, or within 1e-5 m, see *Repeats*).

Bounds
------
Unset bounds are derived from the data's spacing: ``s`` = the median
pose-metric distance from a candidate to its second-nearest other candidate,
each distinct pose counted once (a pose repeated, exactly or within 1e-5 m,
counts as one candidate however often it is repeated);
``max_edge_length`` = :data:`LENGTH_FACTOR` ``* s`` and
``max_edge_angle_deg`` = the angle that counts as :data:`ANGLE_FACTOR` ``* s``
in the pose metric (``ANGLE_FACTOR * s / L`` rad), capped at
:data:`MAX_DEFAULT_ANGLE_DEG`. The length bound is the tighter one because a
long edge is what makes a blended grasp cut into the object: on ACRONYM's mug
(successful grasps, ``benchmarks/bench_interpolation_fidelity.py``) length
factors 1.25 / 1.5 / 2.5 keep 1.00 / 0.96 / 0.82 of the vertices'
non-penetration rate, while the angle factor 2.5 links 99.6 % of them.

Repeats
-------
Rows that are one pose with an earlier row, exactly (also as ``-q``) or
within :data:`~gcm_pipeline.manifold.repeats.NEAR_REPEAT` (1e-5 m in the pose
metric: float32 copies, text round trips, a synthesiser's jittered copies;
:mod:`gcm_pipeline.manifold.repeats`), are set aside before any of this: the
structure is built over the first row of each pose and every other row gets
``family`` -1, ``isolation`` ``duplicate`` and chart ``(0, 0)``. Thousands of
copies of a pose at ~the same place made the k-d tree searches quadratic (a
million rows of 24 poses took minutes; 24,000 rows with 1e-9 m jitter 88 s);
now about a second for a million rows.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from gcm_pipeline.errors import GeometryError
from gcm_pipeline.geometry.bowyer_watson import delaunay
from gcm_pipeline.geometry.dualquat import dq_angle_distance, dq_translation
from gcm_pipeline.geometry.pose_metric import (
    other_sign_features,
    pose_distance,
    pose_features,
)
from gcm_pipeline.manifold.repeats import first_rows, same_pose_rows

__all__ = [
    "BOUND_TOLERANCE",
    "ISOLATION_REASONS",
    "MAX_DEFAULT_ANGLE_DEG",
    "ANGLE_FACTOR",
    "LENGTH_FACTOR",
    "FamilyMesh",
    "default_bounds",
    "family_triangles",
    "first_rows",
]

#: The default ``max_edge_length`` is this many times the data's spacing (module docstring).
LENGTH_FACTOR = 1.25
#: The default ``max_edge_angle_deg`` counts as this many spacings in the pose metric.
ANGLE_FACTOR = 2.5
#: Cap [deg] of the default ``max_edge_angle_deg``.
MAX_DEFAULT_ANGLE_DEG = 60.0
#: Why a candidate is in no triangle (``""``: it is in one).
ISOLATION_REASONS = ("", "duplicate", "no_neighbour", "no_triple")

#: Relative tolerance of the bound tests: a pair at most ``(1 + BOUND_TOLERANCE)`` times
#: a bound is within it. Grasp sets on a lattice (ACRONYM's 30-degree steps) put many pairs
#: exactly on a round bound (60 degrees); without it rounding, which moves with the set's
#: placement in the world and with the CPU, decides whether such a pair is linked.
BOUND_TOLERANCE = 1e-9
_SELF = 1e-9  # [m] a spacing query's hits this near are the row itself (rows repeat none)
_SMALL_FAMILY = 30  # families up to this size are one patch
_GAP = 0.5  # gap between family charts in the atlas, in units of max_edge_length
# The k-d tree searches run in blocks of rows, each one call into scipy's C code: Python
# handles a signal (Ctrl-C, SIGTERM) only between such calls, so a block must be short.
_QUERY_BLOCK = 1 << 12  # rows of one nearest-neighbour query block (the spacing)
_BLOCK_PAIRS = 1 << 19  # hits one block of the neighbour search aims at
_FIRST_BLOCK, _MIN_BLOCK, _MAX_BLOCK = 256, 16, 1 << 16  # rows of those blocks


@dataclass(frozen=True)
class FamilyMesh:
    """The triangles of the ``families`` structure and what it says of each candidate.

    Attributes:
        chart: (N, 2) atlas coordinates [m]: each family's own chart, families
            side by side (for plots; distances between families mean nothing).
        triangles: (T, 3) candidate row ids, every edge within the bounds.
        dropped: (D, 3) chart triangles pruned by the bounds.
        dropped_reason: (D,) ``edge_length`` or ``edge_angle``.
        family: (N,) family id per candidate (-1 for duplicates), largest family 0.
        isolation: (N,) reason a candidate is in no triangle (:data:`ISOLATION_REASONS`).
        max_edge_length: The position bound used [m].
        max_edge_angle_deg: The orientation bound used [deg].
    """

    chart: np.ndarray
    triangles: np.ndarray
    dropped: np.ndarray
    dropped_reason: np.ndarray
    family: np.ndarray
    isolation: np.ndarray
    max_edge_length: float
    max_edge_angle_deg: float


# --------------------------------------------------------------------------- bounds
def default_bounds(
    dq: np.ndarray,
    orientation_scale: float,
    max_edge_length: float | None = None,
    max_edge_angle_deg: float | None = None,
) -> tuple[float, float]:
    """The bounds ``(max_edge_length [m], max_edge_angle_deg)``, unset ones from the spacing.

    The spacing is that of the distinct poses, each once (module docstring, "Bounds").

    Raises:
        GeometryError: If the grasps have fewer than 3 distinct poses (no
            spacing to derive a bound from, nothing to link).
    """
    if max_edge_length is not None and max_edge_angle_deg is not None:
        return float(max_edge_length), float(max_edge_angle_deg)
    first = _distinct_rows(dq, orientation_scale)
    return _bounds(dq[first], len(dq), orientation_scale, max_edge_length, max_edge_angle_deg)


def _bounds(
    dq: np.ndarray,
    total: int,
    orientation_scale: float,
    max_edge_length: float | None,
    max_edge_angle_deg: float | None,
) -> tuple[float, float]:
    """:func:`default_bounds` over rows of which no two are one pose (``total``: rows given)."""
    if len(dq) < 3 and (max_edge_length is None or max_edge_angle_deg is None):
        raise _too_few(total)
    if max_edge_length is not None and max_edge_angle_deg is not None:
        return float(max_edge_length), float(max_edge_angle_deg)
    feats = pose_features(dq, orientation_scale)
    tree = cKDTree(np.concatenate((feats, other_sign_features(feats))))
    k = min(len(feats) * 2, 8)
    # row blocks: each row's answer is its own, and an interrupt is handled between blocks
    dist = np.concatenate(
        [
            tree.query(feats[a : a + _QUERY_BLOCK], k=k)[0]
            for a in range(0, len(feats), _QUERY_BLOCK)
        ]
    ).reshape(len(feats), k)
    # the nearest hit is the row itself (no two rows are one pose): skip zero distances
    nonzero = np.where(dist > _SELF, dist, np.inf)
    nonzero.sort(axis=1)
    second = nonzero[:, 1] if k > 1 else np.full(len(feats), np.inf)
    finite = second[np.isfinite(second)]
    if not len(finite):
        raise _too_few(total)
    spacing = float(np.median(finite))
    length = LENGTH_FACTOR * spacing if max_edge_length is None else float(max_edge_length)
    if max_edge_angle_deg is None:
        turn = ANGLE_FACTOR * spacing / orientation_scale
        angle = min(MAX_DEFAULT_ANGLE_DEG, float(np.degrees(turn)))
    else:
        angle = float(max_edge_angle_deg)
    return length, angle


def _too_few(total: int) -> GeometryError:
    return GeometryError(
        f"the {total} grasps have fewer than 3 distinct poses: nothing to link "
        "(give more grasps, or set manifold.max_edge_length and max_edge_angle_deg)"
    )


def _distinct_rows(dq: np.ndarray, orientation_scale: float) -> np.ndarray:
    """(U,) ascending: the rows that repeat no earlier row (:func:`~.repeats.same_pose_rows`)."""
    rep = same_pose_rows(dq, orientation_scale)
    return np.flatnonzero(rep == np.arange(len(dq)))


# --------------------------------------------------------------------------- graph
def _neighbour_pairs(
    dq: np.ndarray, length: float, angle_deg: float, scale: float
) -> tuple[np.ndarray, np.ndarray]:
    """Sorted unique pairs (P, 2), i < j, within both bounds, and their pose distances.

    The k-d tree is searched in blocks of rows (:func:`_ball_pairs`), so that a
    Ctrl-C or SIGTERM is handled within a block's time, not the whole search's.
    """
    n = len(dq)
    feats = pose_features(dq, scale)
    angle = np.deg2rad(angle_deg)
    radius = np.hypot(length, 4.0 * scale * np.sin(angle / 4.0)) * (1 + 1e-9) + 1e-12
    tree = cKDTree(np.concatenate((feats, other_sign_features(feats))))
    pos = dq_translation(dq)
    tie = 1.0 + BOUND_TOLERANCE  # a pair exactly on a bound is in, however it rounds
    parts = []
    for keys in _ball_pairs(tree, feats, radius):  # ascending blocks of sorted keys
        pairs = np.column_stack((keys // n, keys % n))
        ok = np.linalg.norm(pos[pairs[:, 0]] - pos[pairs[:, 1]], axis=1) <= length * tie
        ok &= dq_angle_distance(dq[pairs[:, 0]], dq[pairs[:, 1]]) <= angle * tie
        parts.append(pairs[ok])
    pairs = np.concatenate(parts).astype(np.int64) if parts else np.zeros((0, 2), np.int64)
    return pairs, pose_distance(dq[pairs[:, 0]], dq[pairs[:, 1]], scale)


def _ball_pairs(tree: cKDTree, feats: np.ndarray, radius: float) -> Iterator[np.ndarray]:
    """The pair keys ``i * n + j`` (i < j) of rows within ``radius`` in ``tree``, by blocks of i.

    ``tree`` holds the (n) features and then their sign-flipped copies; a hit
    ``j >= n`` is row ``j - n``. The same pairs as ``tree.query_pairs(radius)``
    taken modulo n, without a row's pair with its own copy (a pair and its
    flipped twin are one distance, exactly), in one C call per block of rows:
    a block is sized from the previous block's hits per row to about
    :data:`_BLOCK_PAIRS` hits. Each block's keys are sorted and unique, and
    the blocks come in ascending order of i.
    """
    n = len(feats)
    start, size = 0, _FIRST_BLOCK
    while start < n:
        stop = min(n, start + size)
        hits = cKDTree(feats[start:stop]).sparse_distance_matrix(
            tree, radius, output_type="ndarray"
        )
        i = hits["i"].astype(np.int64) + start
        j = hits["j"].astype(np.int64) % n
        keys = np.sort(i[i < j] * n + j[i < j])  # np.unique is 10x slower on these
        yield keys[np.r_[True, keys[1:] != keys[:-1]]] if len(keys) else keys
        per_row = max(len(hits) / (stop - start), 1.0)
        size = int(min(max(_BLOCK_PAIRS / per_row, _MIN_BLOCK), _MAX_BLOCK))
        start = stop


def _pair_keys(a: np.ndarray, b: np.ndarray, n: int) -> np.ndarray:
    return np.minimum(a, b) * n + np.maximum(a, b)


def _has_pair(keys: np.ndarray, a: np.ndarray, b: np.ndarray, n: int) -> np.ndarray:
    """Whether (a, b) are neighbour pairs; ``keys`` sorted pair keys."""
    q = _pair_keys(a, b, n)
    at = np.minimum(np.searchsorted(keys, q), max(len(keys) - 1, 0))
    return (keys[at] == q) if len(keys) else np.zeros(q.shape, dtype=bool)


# --------------------------------------------------------------------------- charts
def _family_chart(feats: np.ndarray) -> np.ndarray:
    """(M, 2) coordinates of a family's pose features on their two principal axes."""
    rel = feats - feats.mean(axis=0)
    if len(rel) < 2:
        return np.zeros((len(rel), 2))
    _, _, vt = np.linalg.svd(rel, full_matrices=False)
    axes = vt[:2].T
    for k in range(axes.shape[1]):  # deterministic signs
        if axes[np.argmax(np.abs(axes[:, k])), k] < 0:
            axes[:, k] *= -1
    out = np.zeros((len(rel), 2))
    out[:, : axes.shape[1]] = rel @ axes
    return out


def _chart_tris(chart: np.ndarray, triangulator: str) -> np.ndarray:
    if len(chart) < 3:
        return np.zeros((0, 3), dtype=np.int64)
    try:
        return delaunay(chart, triangulator)
    except GeometryError:  # collinear family: the fill step links it
        return np.zeros((0, 3), dtype=np.int64)


def _atlas(charts: list[tuple[np.ndarray, np.ndarray]], n: int, gap: float) -> np.ndarray:
    """Lay the family charts side by side in rows (largest first)."""
    out = np.zeros((n, 2))
    boxes = [np.ptp(c, axis=0) if len(c) else np.zeros(2) for _, c in charts]
    width = max(
        float(np.sqrt(sum((b[0] + gap) * (b[1] + gap) for b in boxes))) * 1.5,
        max((b[0] for b in boxes), default=0.0),
    )
    x = y = row_h = 0.0
    for (rows, c), box in zip(charts, boxes, strict=True):
        if x > 0 and x + box[0] > width:
            x, y, row_h = 0.0, y - row_h - gap, 0.0
        out[rows] = c - c.min(axis=0) + (x, y - box[1]) if len(c) else (x, y)
        x += box[0] + gap
        row_h = max(row_h, box[1])
    return out


def _patches(local: np.ndarray, radius: float) -> list[tuple[np.ndarray, np.ndarray]]:
    """Overlapping patches of a family, each small enough for one flat chart.

    Centres are picked greedily (row order) until every row is within
    ``radius / 2`` of one; a patch is the rows within ``radius`` of its centre
    (``ball``, family-local indices) and ``core`` (M,) marks the family rows
    within ``radius / 2`` of it. A family no wider than ``radius`` is one patch.
    """
    m = len(local)
    everything = (np.arange(m), np.ones(m, dtype=bool))
    if m <= _SMALL_FAMILY or float(np.ptp(local, axis=0).max()) <= radius:
        return [everything]
    tree = cKDTree(local)
    covered = np.zeros(m, dtype=bool)
    out = []
    for c in range(m):
        if covered[c]:
            continue
        ball = np.asarray(tree.query_ball_point(local[c], radius), dtype=np.int64)
        near = np.linalg.norm(local[ball] - local[c], axis=1) <= 0.5 * radius
        core = np.zeros(m, dtype=bool)
        core[ball[near]] = True
        covered |= core
        out.append((np.sort(ball), core))
    return out


def _tri_keys(tris: np.ndarray, n: int) -> np.ndarray:
    t = np.sort(tris, axis=1)
    return (t[:, 0] * n + t[:, 1]) * n + t[:, 2]


def _unique_tris(parts: list[np.ndarray]) -> np.ndarray:
    """The triangles of ``parts`` once each (first occurrence, order kept)."""
    parts = [p for p in parts if len(p)]
    if not parts:
        return np.zeros((0, 3), dtype=np.int64)
    tris = np.concatenate(parts).astype(np.int64)
    _, first = np.unique(_tri_keys(tris, int(tris.max()) + 1), return_index=True)
    return tris[np.sort(first)]


# --------------------------------------------------------------------------- fill
def _fill(
    dq: np.ndarray,
    scale: float,
    pairs: np.ndarray,
    dist: np.ndarray,
    keys: np.ndarray,
    covered: np.ndarray,
    candidates: np.ndarray,
) -> list[tuple[int, int, int]]:
    """One triangle for each candidate row still uncovered, where it has one.

    The triangle with the row and two neighbours that are neighbours of each
    other whose longest pose-metric edge is shortest (rows in ``candidates``
    order; the two others count as covered from then on).
    """
    n = len(dq)
    order = np.argsort(np.concatenate((pairs[:, 0], pairs[:, 1])), kind="stable")
    other = np.concatenate((pairs[:, 1], pairs[:, 0]))[order]
    d_other = np.concatenate((dist, dist))[order]
    start = np.searchsorted(np.concatenate((pairs[:, 0], pairs[:, 1]))[order], np.arange(n + 1))
    added: list[tuple[int, int, int]] = []
    for i in candidates:
        if covered[i]:
            continue
        nb, d = other[start[i] : start[i + 1]], d_other[start[i] : start[i + 1]]
        if len(nb) < 2:
            continue
        a, b = np.triu_indices(len(nb), 1)
        ok = _has_pair(keys, nb[a], nb[b], n)
        if not ok.any():
            continue
        a, b = a[ok], b[ok]
        longest = np.maximum(np.maximum(d[a], d[b]), pose_distance(dq[nb[a]], dq[nb[b]], scale))
        best = int(np.argmin(longest))
        tri = (int(i), int(nb[a[best]]), int(nb[b[best]]))
        added.append(tri)
        covered[list(tri)] = True
    return added


def _canonical(tris: np.ndarray) -> np.ndarray:
    """Triangles with ascending vertex ids, in ascending order: the same set, the same rows.

    The charts a family is triangulated in turn with the grasp set (their axes
    are principal axes of world features), so the triangles' order and
    orientation would; their densified rows would too.
    """
    t = np.sort(np.asarray(tris, dtype=np.int64).reshape(-1, 3), axis=1)
    return t[np.lexsort(t.T[::-1])]


# --------------------------------------------------------------------------- stage
def _prune_reason(dq: np.ndarray, tris: np.ndarray, length: float) -> np.ndarray:
    """Why each triangle was pruned: ``edge_length`` (a position edge too long), ``edge_angle``."""
    p = dq_translation(dq)[tris]
    longest = np.linalg.norm(p - np.roll(p, -1, axis=1), axis=2).max(axis=1)
    too_long = longest > length * (1.0 + BOUND_TOLERANCE)  # as the bound tests read it
    return np.where(too_long, "edge_length", "edge_angle").astype("<U11")


def family_triangles(
    dq: np.ndarray,
    *,
    max_edge_length: float | None,
    max_edge_angle_deg: float | None,
    orientation_scale: float,
    triangulator: str = "qhull",
) -> FamilyMesh:
    """Build the ``families`` structure over validated poses (see the module docstring).

    Args:
        dq: (N, 8) unit dual quaternions of the candidates (N >= 3).
        max_edge_length: Position bound [m], or None for the default.
        max_edge_angle_deg: Orientation bound [deg], or None for the default.
        orientation_scale: ``L`` [m/rad] of the pose metric.
        triangulator: ``qhull`` or ``bowyer_watson`` for the family charts.

    Raises:
        GeometryError: Fewer than 3 distinct poses when a bound is to be derived.
    """
    first = _distinct_rows(dq, orientation_scale)
    bounds = _bounds(dq[first], len(dq), orientation_scale, max_edge_length, max_edge_angle_deg)
    if len(first) == len(dq):
        return _family_mesh(dq, *bounds, orientation_scale, triangulator)
    # repeats: the distinct poses alone (a k-d tree over thousands of copies of one
    # point searches for minutes), each repeat a duplicate of its pose's first row
    one = _family_mesh(dq[first], *bounds, orientation_scale, triangulator)
    n = len(dq)
    chart = np.zeros((n, 2))
    chart[first] = one.chart
    family = np.full(n, -1, dtype=np.int64)
    family[first] = one.family
    isolation = np.full(n, "duplicate", dtype=one.isolation.dtype)
    isolation[first] = one.isolation
    return FamilyMesh(
        chart=chart,
        triangles=first[one.triangles],  # first is ascending: the order is kept
        dropped=first[one.dropped],
        dropped_reason=one.dropped_reason,
        family=family,
        isolation=isolation,
        max_edge_length=one.max_edge_length,
        max_edge_angle_deg=one.max_edge_angle_deg,
    )


def _family_mesh(
    dq: np.ndarray, length: float, angle: float, orientation_scale: float, triangulator: str
) -> FamilyMesh:
    """:func:`family_triangles` with its bounds, over rows of which no two are one pose."""
    n = len(dq)
    pairs, dist = _neighbour_pairs(dq, length, angle, orientation_scale)
    keys = np.sort(_pair_keys(pairs[:, 0], pairs[:, 1], n))
    graph = coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(n, n))
    _, label = connected_components(graph, directed=False)
    # families numbered by size (largest first), ties by first row
    fam_rows = [np.flatnonzero(label == lab) for lab in np.unique(label)]
    fam_rows.sort(key=lambda r: (-len(r), int(r[0])))
    family = np.full(n, -1, dtype=np.int64)
    feats = pose_features(dq, orientation_scale)
    charts: list[tuple[np.ndarray, np.ndarray]] = []
    kept: list[np.ndarray] = []
    dropped: list[np.ndarray] = []
    reach = float(np.hypot(length, 4.0 * orientation_scale * np.sin(np.deg2rad(angle) / 4.0)))
    for f, rows in enumerate(fam_rows):
        family[rows] = f
        r = dq[rows, :4]
        sign = np.where(r @ r[0] < 0, -1.0, 1.0)
        local = np.concatenate((feats[rows, :3], (2.0 * orientation_scale) * sign[:, None] * r), 1)
        charts.append((rows, _family_chart(local)))
        for ball, core in _patches(local, 1.5 * reach):
            chart = charts[-1][1] if len(ball) == len(rows) else _family_chart(local[ball])
            tris = ball[_chart_tris(chart, triangulator)]
            tris = tris[core[tris].any(axis=1)] if len(tris) else tris
            ok = np.ones(len(tris), dtype=bool)
            for a, b in ((0, 1), (1, 2), (2, 0)):
                ok &= _has_pair(keys, rows[tris[:, a]], rows[tris[:, b]], n)
            kept.append(rows[tris[ok]])
            dropped.append(rows[tris[~ok]])
    tris = _unique_tris(kept)
    dropped_tris = _unique_tris(dropped)
    if len(dropped_tris) and len(tris):  # pruned in one patch, kept in another
        dropped_tris = dropped_tris[~np.isin(_tri_keys(dropped_tris, n), _tri_keys(tris, n))]
    covered = np.zeros(n, dtype=bool)
    covered[tris.ravel()] = True
    extra = _fill(dq, orientation_scale, pairs, dist, keys, covered, np.arange(n))
    if extra:
        tris = np.concatenate((tris, np.asarray(extra, dtype=np.int64)))
    degree = np.bincount(pairs.ravel(), minlength=n)
    isolation = np.full(n, "", dtype="<U12")
    isolation[~covered & (degree > 0)] = "no_triple"
    isolation[~covered & (degree == 0)] = "no_neighbour"
    return FamilyMesh(
        chart=_atlas(charts, n, _GAP * length),
        triangles=_canonical(tris),
        dropped=dropped_tris.astype(np.int64),
        dropped_reason=_prune_reason(dq, dropped_tris, length),
        family=family,
        isolation=isolation,
        max_edge_length=length,
        max_edge_angle_deg=angle,
    )
