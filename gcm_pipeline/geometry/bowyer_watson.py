"""Planar Delaunay triangulation: Qhull (default) and the paper's Bowyer-Watson.

:func:`delaunay` is the entry point. ``method="qhull"`` uses
:class:`scipy.spatial.Delaunay`; ``method="bowyer_watson"`` runs
:func:`bowyer_watson`, the incremental algorithm the reference paper
(section II-C) uses, written here on purpose so the method can be reproduced
and compared.

Bowyer-Watson, as implemented
-----------------------------
* Points are validated, duplicates are dropped (the first occurrence is
  kept, as Qhull does) and coordinates are scaled uniformly into the unit
  box, so the float64 predicates work on numbers of order one.
* The super-triangle is a single vertex at infinity (its three corners
  pushed to infinity): a triangle touching it is a *ghost* triangle
  ``(u, v, inf)`` over a convex-hull edge, whose "circumcircle" is the open
  half-plane beyond ``u -> v`` (plus the open segment ``uv`` itself). This is
  the limit of an ever larger super-triangle and avoids its classic failure
  (missing hull edges when its corners are too close). Triangles touching it
  are removed at the end, as in the paper.
* Insertion order is BRIO (random rounds of doubling size, Amenta et al.)
  with each round sorted along a Hilbert curve, so consecutive points are
  close. The containing triangle is found by a visibility walk from the last
  inserted triangle (no scan over all triangles), the cavity grows by
  breadth-first search over neighbours whose circumcircle contains the point,
  and the cavity boundary is connected to the point. Expected cost close to
  O(n log n).
* Predicates: orientation and incircle determinants in float64 with a
  relative error bound; near-ties count as "not inside", so co-circular
  points (grids) are triangulated consistently. A cavity is grown further if
  a boundary edge is not strictly visible from the new point, so no
  inverted triangle is created even on near-degenerate input.

Triangles are returned counter-clockwise as rows of original point indices.
"""

from __future__ import annotations

import numpy as np
import numpy.typing as npt
from scipy.spatial import Delaunay, QhullError

from gcm_pipeline.errors import GeometryError, choice_error

__all__ = ["TRIANGULATORS", "bowyer_watson", "check_triangulable", "delaunay"]

TRIANGULATORS = ("bowyer_watson", "qhull")

_INCIRCLE_EPS = 1e-12
_ORIENT_EPS = 1e-13
_COLLINEAR_RATIO = 1e-10


# --------------------------------------------------------------------------- input
def _prepare(points: npt.ArrayLike) -> tuple[np.ndarray, np.ndarray]:
    """Validate 2-D points, drop duplicates, scale into the unit box.

    Returns:
        ``(unit, ids)``: distinct points scaled uniformly into [0, 1]^2 (U, 2)
        and their row indices in the input (U,), first occurrences, ascending.
    """
    pts = np.asarray(points, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] != 2:
        raise GeometryError(f"points must have shape (N, 2), got {pts.shape}")
    if not np.isfinite(pts).all():
        i = int(np.argmax(~np.isfinite(pts).all(axis=1)))
        raise GeometryError(f"points have non-finite values at row {i}: {pts[i].tolist()}")
    if len(pts) < 3:
        raise GeometryError(f"need at least 3 points to triangulate, got {len(pts)}")
    srt = np.lexsort((pts[:, 1], pts[:, 0]))  # stable: first occurrence leads each group
    same = (pts[srt[1:]] == pts[srt[:-1]]).all(axis=1)
    ids = np.sort(srt[np.concatenate(([True], ~same))])
    if len(ids) < 3:
        raise GeometryError(
            f"points are degenerate: only {len(ids)} distinct of {len(pts)} (all duplicates)"
        )
    uniq = pts[ids]
    lo = uniq.min(axis=0)
    scale = float((uniq.max(axis=0) - lo).max())
    unit = (uniq - lo) / scale
    centred = unit - unit.mean(axis=0)
    evals = np.linalg.eigvalsh(centred.T @ centred)
    if evals[0] <= (_COLLINEAR_RATIO**2) * evals[1]:
        raise GeometryError(f"points are degenerate: all {len(ids)} distinct points are collinear")
    return unit, ids


def check_triangulable(points: npt.ArrayLike) -> None:
    """Raise if :func:`delaunay` cannot triangulate ``points``.

    Args:
        points: Points (N, 2).

    Raises:
        GeometryError: On a wrong shape, non-finite values, fewer than 3
            points, or points that are all duplicates or all collinear.
    """
    _prepare(points)


def _ccw(points: np.ndarray, tris: np.ndarray) -> np.ndarray:
    """Reorder triangles (T, 3) counter-clockwise."""
    a, b, c = points[tris[:, 0]], points[tris[:, 1]], points[tris[:, 2]]
    area2 = (b[:, 0] - a[:, 0]) * (c[:, 1] - a[:, 1]) - (b[:, 1] - a[:, 1]) * (c[:, 0] - a[:, 0])
    out = tris.copy()
    neg = area2 < 0
    out[neg, 1], out[neg, 2] = tris[neg, 2], tris[neg, 1]
    return out


# --------------------------------------------------------------------------- ordering
def _hilbert_index(x: np.ndarray, y: np.ndarray, order: int = 16) -> np.ndarray:
    """Distance along a Hilbert curve of integer grid coordinates in [0, 2**order).

    The classic bit-by-bit conversion, vectorised over the points. Reflections
    use ``s - 1 - x`` instead of ``2**order - 1 - x``: both agree on the bits
    below ``s``, the only ones read afterwards.
    """
    x = x.astype(np.int64)
    y = y.astype(np.int64)
    d = np.zeros(x.shape, dtype=np.int64)
    s = 1 << (order - 1)
    while s > 0:
        rx = (x & s) > 0
        ry = (y & s) > 0
        d += s * s * ((3 * rx) ^ ry)
        flip = rx & ~ry
        x = np.where(flip, s - 1 - x, x)
        y = np.where(flip, s - 1 - y, y)
        x, y = np.where(ry, x, y), np.where(ry, y, x)
        s >>= 1
    return d


def _brio_order(unit: np.ndarray, seed: int) -> np.ndarray:
    """Biased randomised insertion order: rounds of doubling size, Hilbert-sorted."""
    n = len(unit)
    rng = np.random.default_rng(seed)
    perm = rng.permutation(n)
    grid = np.minimum((unit * 65535.0).astype(np.int64), 65535)
    h = _hilbert_index(grid[:, 0], grid[:, 1])
    bounds = [n]
    while bounds[-1] > 64:
        bounds.append(bounds[-1] // 2)
    bounds.append(0)
    bounds.reverse()
    rounds = []
    for lo, hi in zip(bounds[:-1], bounds[1:], strict=True):
        chunk = perm[lo:hi]
        rounds.append(chunk[np.argsort(h[chunk], kind="stable")])
    return np.concatenate(rounds)


# --------------------------------------------------------------------------- Bowyer-Watson
def bowyer_watson(points: npt.ArrayLike, *, seed: int = 0) -> np.ndarray:
    """Delaunay triangulation by the Bowyer-Watson algorithm (the paper's method).

    Args:
        points: Points (N, 2), any units (scaled uniformly internally).
        seed: Seed of the randomised insertion order (the result is the same
            Delaunay triangulation for points in general position).

    Returns:
        Triangles (T, 3) int64, counter-clockwise, rows of point indices.
        Duplicate points are not used (the first occurrence is).

    Raises:
        GeometryError: On non-finite values, fewer than 3 points, or points
            that are all duplicates or all collinear.
    """
    unit, ids = _prepare(points)
    order = _brio_order(unit, seed)
    tris = _bowyer_watson_core(unit, order)
    return ids[tris]


# One function over 100 lines on purpose: the insertion loop and its helpers share local
# lists through closures, the cheapest access pure Python has in this hot loop.
def _bowyer_watson_core(unit: np.ndarray, order: np.ndarray) -> np.ndarray:  # noqa: C901
    """Insert ``unit[order]`` one by one; return ccw triangles (T, 3) into ``unit``."""
    n = len(unit)
    xs: list[float] = unit[:, 0].tolist()
    ys: list[float] = unit[:, 1].tolist()
    ghost = n  # the vertex at infinity (super-triangle corners)
    ins: list[int] = order.tolist()

    def orient(a: int, b: int, c: int) -> float:
        """Twice the signed area of (a, b, c); 0 within the float error bound."""
        ax, ay = xs[a], ys[a]
        t1 = (xs[b] - ax) * (ys[c] - ay)
        t2 = (ys[b] - ay) * (xs[c] - ax)
        det = t1 - t2
        if abs(det) <= _ORIENT_EPS * (abs(t1) + abs(t2)):
            return 0.0
        return det

    # Initial triangle: the first point, the second, the first one not collinear.
    p0, p1 = ins[0], ins[1]
    k = 2
    while orient(p0, p1, ins[k]) == 0.0:
        k += 1
    p2 = ins.pop(k)
    if orient(p0, p1, p2) < 0:
        p1, p2 = p2, p1
    rest = ins[2:]

    # Flattened storage: vertices tv[3t + i], neighbour across edge (v_i, v_i+1) tn[3t + i].
    tv: list[int] = [p0, p1, p2, p1, p0, ghost, p2, p1, ghost, p0, p2, ghost]
    tn: list[int] = [1, 2, 3, 0, 3, 2, 0, 1, 3, 0, 2, 1]
    # Ghost (u, v, inf) lies beyond hull edge u -> v; ghosts are linked around infinity.
    free: list[int] = []
    mark: list[int] = [-1, -1, -1, -1]
    last = 0

    def in_circle(t: int, p: int) -> bool:
        """Whether p is strictly inside the circumcircle of triangle t (ghosts: half-plane)."""
        a, b, c = tv[3 * t], tv[3 * t + 1], tv[3 * t + 2]
        if c == ghost or a == ghost or b == ghost:
            if c == ghost:
                u, v = a, b
            elif a == ghost:
                u, v = b, c
            else:
                u, v = c, a
            o = orient(u, v, p)
            if o != 0.0:
                return o > 0.0
            ux, uy, vx, vy, px, py = xs[u], ys[u], xs[v], ys[v], xs[p], ys[p]
            return (px - ux) * (vx - ux) + (py - uy) * (vy - uy) > 0.0 and (px - vx) * (ux - vx) + (
                py - vy
            ) * (uy - vy) > 0.0
        px, py = xs[p], ys[p]
        adx, ady = xs[a] - px, ys[a] - py
        bdx, bdy = xs[b] - px, ys[b] - py
        cdx, cdy = xs[c] - px, ys[c] - py
        alift = adx * adx + ady * ady
        blift = bdx * bdx + bdy * bdy
        clift = cdx * cdx + cdy * cdy
        bc1, bc2 = bdx * cdy, cdx * bdy
        ca1, ca2 = cdx * ady, adx * cdy
        ab1, ab2 = adx * bdy, bdx * ady
        det = alift * (bc1 - bc2) + blift * (ca1 - ca2) + clift * (ab1 - ab2)
        perm = (
            alift * (abs(bc1) + abs(bc2))
            + blift * (abs(ca1) + abs(ca2))
            + clift * (abs(ab1) + abs(ab2))
        )
        return det > _INCIRCLE_EPS * perm

    def locate(p: int, t: int) -> int:
        """Visibility walk from t to a triangle containing p (a ghost if p is outside)."""
        if ghost in (tv[3 * t], tv[3 * t + 1], tv[3 * t + 2]):
            for i in range(3):
                if tv[3 * t + i] != ghost and tv[3 * t + (i + 1) % 3] != ghost:
                    t = tn[3 * t + i]
                    break
        turn = 0
        for _ in range(4 * n + 16):
            base = 3 * t
            for j in range(3):
                i = (j + turn) % 3
                if orient(tv[base + i], tv[base + (i + 1) % 3], p) < 0.0:
                    t = tn[base + i]
                    break
            else:
                return t
            turn += 1
            if ghost in (tv[3 * t], tv[3 * t + 1], tv[3 * t + 2]):
                return t
        # Unreachable for a valid triangulation; fall back to a scan.
        for t in range(len(tv) // 3):  # pragma: no cover
            if tv[3 * t] >= 0 and in_circle(t, p):
                return t
        raise GeometryError("Bowyer-Watson point location failed")  # pragma: no cover

    for stamp, p in enumerate(rest):
        start = locate(p, last)
        cavity = [start]
        mark[start] = stamp
        stack = [start]
        while stack:
            t = stack.pop()
            for i in range(3):
                nb = tn[3 * t + i]
                if mark[nb] != stamp and in_circle(nb, p):
                    mark[nb] = stamp
                    cavity.append(nb)
                    stack.append(nb)
        # Boundary edges (u, v) with the triangle outside; grow until all are visible from p.
        while True:
            boundary = []
            grown = False
            for t in cavity:
                for i in range(3):
                    nb = tn[3 * t + i]
                    if mark[nb] == stamp:
                        continue
                    u, v = tv[3 * t + i], tv[3 * t + (i + 1) % 3]
                    if u != ghost and v != ghost and orient(u, v, p) <= 0.0:
                        mark[nb] = stamp
                        cavity.append(nb)
                        grown = True
                        break
                    boundary.append((u, v, nb, t))
                if grown:
                    break
            if not grown:
                break
        # Retriangulate: one new triangle (u, v, p) per boundary edge, reusing slots.
        free.extend(cavity)
        by_first: dict[int, int] = {}
        by_second: dict[int, int] = {}
        new: list[int] = []
        for u, v, nb, old in boundary:
            if free:
                t = free.pop()
            else:
                t = len(tv) // 3
                tv.extend((0, 0, 0))
                tn.extend((0, 0, 0))
                mark.append(-1)
            tv[3 * t], tv[3 * t + 1], tv[3 * t + 2] = u, v, p
            tn[3 * t] = nb
            for j in range(3):
                if tn[3 * nb + j] == old and tv[3 * nb + (j + 1) % 3] == u:
                    tn[3 * nb + j] = t
                    break
            by_first[u] = t
            by_second[v] = t
            new.append(t)
        for t in new:
            tn[3 * t + 1] = by_first[tv[3 * t + 1]]
            tn[3 * t + 2] = by_second[tv[3 * t]]
            mark[t] = -1
        for t in free:
            tv[3 * t] = -1
            mark[t] = -1
        last = new[0]
        for t in new:
            if ghost not in (tv[3 * t], tv[3 * t + 1]):
                last = t
                break

    arr = np.asarray(tv, dtype=np.int64).reshape(-1, 3)
    keep = (arr[:, 0] >= 0) & (arr != ghost).all(axis=1)
    return arr[keep]


# --------------------------------------------------------------------------- entry point
def delaunay(points: npt.ArrayLike, method: str = "qhull") -> np.ndarray:
    """Delaunay triangulation of planar points.

    Args:
        points: Points (N, 2), e.g. chart coordinates [m].
        method: ``"qhull"`` (:class:`scipy.spatial.Delaunay`, default) or
            ``"bowyer_watson"`` (:func:`bowyer_watson`, the paper's algorithm).

    Returns:
        Triangles (T, 3) int64, counter-clockwise, rows of point indices.
        Duplicate points are left out (their first occurrence is used).

    Raises:
        GeometryError: On an unknown method, non-finite values, fewer than 3
            points, or points that are all duplicates or all collinear.
    """
    if method not in TRIANGULATORS:
        raise choice_error(GeometryError, "triangulator", method, TRIANGULATORS)
    if method == "bowyer_watson":
        return bowyer_watson(points)
    unit, ids = _prepare(points)
    grid = np.minimum((unit * 65535.0).astype(np.int64), 65535)
    order = np.argsort(_hilbert_index(grid[:, 0], grid[:, 1]))  # spatial order: faster Qhull
    try:
        tri = order[Delaunay(unit[order]).simplices]
    except QhullError as exc:  # pragma: no cover - degeneracies are caught above
        msg = str(exc).strip().splitlines()[0] if str(exc).strip() else "failed"
        raise GeometryError(f"Qhull triangulation failed: {msg}") from exc
    return ids[_ccw(unit, tri)]
