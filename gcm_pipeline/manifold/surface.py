r"""The blended triangles of the grasp manifold: evaluation and projection.

A kept triangle with vertex poses :math:`\hat q_0, \hat q_1, \hat q_2` is a
*surface* of poses: every weight triple :math:`w` (barycentric, ``w >= 0``,
summing to 1) is the grasp :math:`S(w) = \mathrm{DLB}(w; \hat q_0, \hat q_1,
\hat q_2)` (or DIB). Densification samples it on a lattice; this module
evaluates it anywhere (:func:`blend`) and projects poses onto it
(:func:`project_onto_triangles`); distances are those of the pose metric
(:mod:`gcm_pipeline.geometry.pose_metric`). :mod:`gcm_pipeline.manifold.locate`
finds the nearest point of a whole set of such triangles.

Projection
----------

A projection runs a few sequential quadratic programming steps on the
barycentric weights: the blend surface is linearised (DLB: analytic Jacobian
of the normalised blend; DIB: finite differences) and the Gauss-Newton model
is minimised exactly over the triangle (interior, else the best point of the
three edges). It starts from the query's foot point in the triangle's plane.
A step is halved until the point it reaches is nearer than the current one
(far from a triangle the Gauss-Newton model overshoots, to a corner farther
than the start), so a projection never ends farther than where it started;
a triangle that the query's quaternion may meet with either sign is projected
once with each sign held. The result is a local minimum: far from the
manifold a triangle can hold several.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from gcm_pipeline.errors import GeometryError, choice_error
from gcm_pipeline.geometry.dualquat import dq_translation, quat_mul
from gcm_pipeline.geometry.pose_blend import dib, dlb
from gcm_pipeline.geometry.pose_metric import ORIENTATION_SCALE, pose_distance

__all__ = ["BLEND_METHODS", "blend", "project_onto_triangles"]

BLEND_METHODS = ("dib", "dlb")

_QCONJ = np.array([1.0, -1.0, -1.0, -1.0])


def blend(corners: np.ndarray, weights: np.ndarray, method: str = "dlb") -> np.ndarray:
    """Poses (M, 8) of barycentric weights (M, 3) in triangles with corners (M, 3, 8).

    A weight row with a single 1 returns that corner bit for bit (the
    triangle's vertex), whatever the method.

    Raises:
        GeometryError: Unknown method (the weights are trusted: >= 0, sum 1).
    """
    if method not in BLEND_METHODS:
        raise choice_error(GeometryError, "blend method", method, BLEND_METHODS)
    corners = np.asarray(corners, dtype=np.float64)
    weights = np.asarray(weights, dtype=np.float64)
    if method == "dlb":
        out = dlb(corners, weights, check=False)
    else:
        out = dib(corners, weights, check=False)
    vertex = weights == 1.0
    rows = np.flatnonzero(vertex.any(axis=1))
    if rows.size:
        out[rows] = corners[rows, np.argmax(vertex[rows], axis=1)]
    return out


# --------------------------------------------------------------------------- projection
def _dlb_model(
    corners: np.ndarray, uv: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """DLB surface at ``uv`` (P, 2): position (P, 3), rotation (P, 4) and their Jacobians.

    ``w = (1 - u - v, u, v)``; signs aligned to the heaviest corner as
    :func:`~gcm_pipeline.geometry.pose_blend.dlb` does. The blend ``b`` is
    affine in (u, v); ``r = b_r / |b_r|`` and ``p = vec(2 b_d b_r^*) / |b_r|^2``.

    Returns:
        ``p`` (P, 3), ``r`` (P, 4), ``dp`` (P, 3, 2), ``dr`` (P, 4, 2).
    """
    w = np.column_stack((1.0 - uv[:, 0] - uv[:, 1], uv[:, 0], uv[:, 1]))
    piv = np.argmax(w, axis=1)
    rpiv = corners[np.arange(len(w)), piv, :4]
    sign = np.where(np.einsum("pkc,pc->pk", corners[:, :, :4], rpiv) < 0, -1.0, 1.0)
    c = corners * sign[:, :, None]
    b = np.einsum("pk,pkc->pc", w, c)
    db = np.stack((c[:, 1] - c[:, 0], c[:, 2] - c[:, 0]), axis=-1)  # (P, 8, 2)
    return _dlb_of_blend(b, db)


def _dlb_aligned(corners: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Corners (P, 3, 8) signed once for every ``(u, v)`` of :func:`_dlb_model`.

    DLB signs the corners to agree with the heaviest one. Where the three
    rotations, signed to agree with the first corner, agree pairwise (positive
    dot products), signing them to any other corner only flips the blend as a
    whole, which changes neither the pose nor the Gauss-Newton model (its
    residual and Jacobian flip together): the blend is then affine in
    ``(u, v)`` with these coefficients for the whole projection.

    Returns:
        ``base`` (P, 8) (the first corner), ``db`` (P, 8, 2) (the other two
        minus it, signed) and ``ok`` (P,): the signs hold for every ``(u, v)``.
    """
    r = corners[:, :, :4]
    s1 = np.where(np.einsum("pc,pc->p", r[:, 1], r[:, 0]) < 0, -1.0, 1.0)
    s2 = np.where(np.einsum("pc,pc->p", r[:, 2], r[:, 0]) < 0, -1.0, 1.0)
    c1 = corners[:, 1] * s1[:, None]
    c2 = corners[:, 2] * s2[:, None]
    base = corners[:, 0]
    ok = (
        (np.einsum("pc,pc->p", c1[:, :4], base[:, :4]) > 0)
        & (np.einsum("pc,pc->p", c2[:, :4], base[:, :4]) > 0)
        & (np.einsum("pc,pc->p", c1[:, :4], c2[:, :4]) > 0)
    )
    return base, np.stack((c1 - base, c2 - base), axis=-1), ok


def _dlb_affine_model(
    base: np.ndarray, db: np.ndarray, uv: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """As :func:`_dlb_model`, with the corners signed once (:func:`_dlb_aligned`)."""
    b = base + db[:, :, 0] * uv[:, :1] + db[:, :, 1] * uv[:, 1:]
    return _dlb_of_blend(b, db)


def _dlb_of_blend(
    b: np.ndarray, db: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Position, rotation and Jacobians of the normalised blend ``b`` (P, 8), ``db`` (P, 8, 2)."""
    a, e = b[:, :4], b[:, 4:]
    da, de = db[:, :4], db[:, 4:]
    n2 = np.einsum("pc,pc->p", a, a)
    n = np.sqrt(n2)
    r = a / n[:, None]
    a_conj = a * _QCONJ
    m = 2.0 * quat_mul(e, a_conj)  # 2 e a*, its vector part / n2 is p
    p = m[:, 1:] / n2[:, None]
    dn2 = 2.0 * np.einsum("pc,pcj->pj", a, da)  # (P, 2)
    dp = np.empty((len(b), 3, 2))
    dr = np.empty((len(b), 4, 2))
    for j in range(2):
        dm = 2.0 * (quat_mul(de[:, :, j], a_conj) + quat_mul(e, da[:, :, j] * _QCONJ))
        dp[:, :, j] = (dm[:, 1:] - p * dn2[:, j : j + 1]) / n2[:, None]
        dr[:, :, j] = da[:, :, j] / n[:, None] - r * (0.5 * dn2[:, j] / n2)[:, None]
    return p, r, dp, dr


def _dib_model(
    corners: np.ndarray, uv: np.ndarray, step: float = 1e-6
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """As :func:`_dlb_model` for DIB, Jacobians by forward differences (inward)."""
    w = np.column_stack((1.0 - uv[:, 0] - uv[:, 1], uv[:, 0], uv[:, 1]))
    base = dib(corners, w, check=False)
    p, r = dq_translation(base), base[:, :4]
    dp = np.empty((len(w), 3, 2))
    dr = np.empty((len(w), 4, 2))
    for j in range(2):
        h = np.where(uv.sum(axis=1) + step > 1.0, -step, step)  # stay inside the triangle
        wj = w.copy()
        wj[:, j + 1] += h
        wj[:, 0] -= h
        moved = dib(corners, wj, check=False)
        rj = moved[:, :4] * np.where(np.einsum("pc,pc->p", moved[:, :4], r) < 0, -1.0, 1.0)[:, None]
        dp[:, :, j] = (dq_translation(moved) - p) / h[:, None]
        dr[:, :, j] = (rj - r) / h[:, None]
    return p, r, dp, dr


def _qp_triangle(x: np.ndarray, h: np.ndarray, g: np.ndarray) -> np.ndarray:
    """Minimise ``0.5 d^T H d + g^T d`` over ``x + d`` in the triangle u, v >= 0, u + v <= 1.

    Args:
        x: Current points (P, 2).
        h: Hessians (P, 2, 2), positive semi-definite.
        g: Gradients (P, 2).

    Returns:
        The minimisers (P, 2), exact for the quadratic model.
    """
    reg = 1e-12 * (np.trace(h, axis1=1, axis2=2) + 1e-30)
    hh = h + reg[:, None, None] * np.eye(2)
    det = hh[:, 0, 0] * hh[:, 1, 1] - hh[:, 0, 1] * hh[:, 1, 0]
    inv = (
        np.stack(
            (
                np.stack((hh[:, 1, 1], -hh[:, 0, 1]), axis=-1),
                np.stack((-hh[:, 1, 0], hh[:, 0, 0]), axis=-1),
            ),
            axis=1,
        )
        / det[:, None, None]
    )
    free = x - np.einsum("pij,pj->pi", inv, g)
    inside = (free[:, 0] >= 0) & (free[:, 1] >= 0) & (free.sum(axis=1) <= 1)
    out = free
    if inside.all():
        return out
    rows = np.flatnonzero(~inside)
    xr, hr, gr = x[rows], h[rows], g[rows]
    corners = np.array([[0.0, 0.0], [1.0, 0.0], [0.0, 1.0]])
    best = np.full(len(rows), np.inf)
    best_pt = np.zeros((len(rows), 2))
    for a_i, b_i in ((0, 1), (1, 2), (2, 0)):
        a, b = corners[a_i], corners[b_i]
        # point a + s (b - a); model value as a quadratic in s
        d0 = a - xr  # step to a
        e = b - a
        he = np.einsum("pij,j->pi", hr, e)
        curv = np.einsum("j,pj->p", e, he)
        slope = np.einsum("pj,pj->p", gr, np.broadcast_to(e, gr.shape)) + np.einsum(
            "pj,pj->p", d0, he
        )
        s = np.clip(np.where(curv > 0, -slope / np.where(curv > 0, curv, 1.0), 0.0), 0.0, 1.0)
        # with zero curvature pick the better end
        flat = curv <= 0
        s = np.where(flat, np.where(slope < 0, 1.0, 0.0), s)
        pt = a + s[:, None] * e
        d = pt - xr
        val = 0.5 * np.einsum("pi,pij,pj->p", d, hr, d) + np.einsum("pi,pi->p", gr, d)
        better = val < best
        best = np.where(better, val, best)
        best_pt[better] = pt[better]
    out = out.copy()
    out[rows] = best_pt
    return out


def project_onto_triangles(
    queries: np.ndarray,
    corners: np.ndarray,
    uv0: np.ndarray,
    *,
    method: str = "dlb",
    orientation_scale: float = ORIENTATION_SCALE,
    iterations: int = 32,
    tolerance: float = 1e-8,
) -> tuple[np.ndarray, np.ndarray]:
    """Nearest point of each blended triangle to a query pose (local minimum, batched).

    Args:
        queries: (P, 8) query poses, one per pair.
        corners: (P, 3, 8) the triangle's vertex poses, one per pair.
        uv0: (P, 2) starting weights ``(w1, w2)`` (e.g. of the nearest lattice point).
        method: The blend, ``dlb`` or ``dib``.
        orientation_scale: ``L`` [m/rad] of the pose metric.
        iterations: Maximum SQP steps.
        tolerance: Stop when no pair moves more than this in (u, v).

    Returns:
        ``(weights (P, 3), distance (P,))``: the local minimiser and its
        pose-metric distance [m] (from the exact blend, :func:`blend`).
    """
    signed = _signed_to_first(corners)
    if method == "dlb":
        # corners signed once where that holds for every weight (the same
        # model either way, up to rounding; chosen per triangle, never per batch)
        base, db, ok = _dlb_aligned(corners)

        def model(rows: np.ndarray, uv: np.ndarray) -> tuple[np.ndarray, ...]:
            fast = ok[rows]
            if fast.all():
                return _dlb_affine_model(base[rows], db[rows], uv)
            out = tuple(np.empty((len(rows), *shape)) for shape in ((3,), (4,), (3, 2), (4, 2)))
            for sel, part in (
                (fast, _dlb_affine_model(base[rows[fast]], db[rows[fast]], uv[fast])),
                (~fast, _dlb_model(corners[rows[~fast]], uv[~fast])),
            ):
                for whole, piece in zip(out, part, strict=True):
                    whole[sel] = piece
            return out

    else:
        # DIB signs its output like the heaviest corner: a triangle with a corner of
        # the other sign would change sign inside (a jump for a held sign); signed
        # to agree with the first, the same poses keep one sign

        def model(rows: np.ndarray, uv: np.ndarray) -> tuple[np.ndarray, ...]:
            return _dib_model(signed[rows], uv)

    # a pair whose surface may meet the query's quaternion with either sign (a
    # corner's dot product with it is not of the others' sign) has a kink where
    # the nearer sign switches, and a local minimum on each side of it: it is
    # projected once with each sign held (the nearer end is kept)
    dots = np.einsum("pkc,pc->pk", signed[:, :, :4], queries[:, :4])
    two = np.flatnonzero((dots.min(axis=1) <= 0.0) & (dots.max(axis=1) >= 0.0))
    pair = np.concatenate((np.arange(len(queries)), two))
    held = np.zeros(len(pair))
    held[len(queries) :] = -1.0
    held[two] = 1.0
    uv = np.array(uv0, dtype=np.float64)[pair]
    _descend(
        model,
        dq_translation(queries)[pair],
        queries[pair, :4],
        pair,
        uv,
        held,
        2.0 * orientation_scale,
        iterations,
        tolerance,
    )
    w = np.column_stack((1.0 - uv[:, 0] - uv[:, 1], uv[:, 0], uv[:, 1]))
    w = np.clip(w, 0.0, 1.0)
    w /= w.sum(axis=1, keepdims=True)
    w = _snap(w)
    d = pose_distance(blend(corners[pair], w, method), queries[pair], orientation_scale)
    n = len(queries)
    other = d[n:] < d[two]
    w_out, d_out = w[:n], d[:n]
    w_out[two[other]], d_out[two[other]] = w[n:][other], d[n:][other]
    return w_out, d_out


def _signed_to_first(corners: np.ndarray) -> np.ndarray:
    """A triangle's corners (P, 3, 8), each signed so its rotation agrees with the first's."""
    r = corners[:, :, :4]
    return corners * np.where(np.einsum("pkc,pc->pk", r, r[:, 0]) < 0, -1.0, 1.0)[:, :, None]


def _descend(
    model: Callable[[np.ndarray, np.ndarray], tuple[np.ndarray, ...]],
    p_q: np.ndarray,
    r_q: np.ndarray,
    pair: np.ndarray,
    uv: np.ndarray,
    held: np.ndarray,
    scale: float,
    iterations: int,
    tolerance: float,
) -> None:
    """Gauss-Newton steps on ``uv`` (K, 2) in place, each taken only where it descends.

    Row k projects query ``(p_q[k], r_q[k])`` onto the surface of pair
    ``pair[k]`` (``model``'s rows); ``held[k]`` is the sign of the query's
    quaternion held throughout (0: the nearer one at each step).
    """

    def signs(k: np.ndarray, r: np.ndarray) -> np.ndarray:
        free = np.where(np.einsum("pc,pc->p", r, r_q[k]) < 0, -1.0, 1.0)
        return np.where(held[k] == 0.0, free, held[k])

    def cost(k: np.ndarray, p: np.ndarray, r: np.ndarray) -> np.ndarray:
        """Squared pose distance of surface points (p, r) to the queries ``k``."""
        dr = r - signs(k, r)[:, None] * r_q[k]
        return np.sum((p - p_q[k]) ** 2, axis=1) + scale**2 * np.sum(dr**2, axis=1)

    active = np.arange(len(uv))
    at = model(pair, uv)  # the surface at uv[active], with its Jacobians
    for _ in range(iterations):
        if not active.size:
            break
        p, r, dp, dr = at
        sign = signs(active, r)
        res = np.concatenate((p - p_q[active], scale * (r - sign[:, None] * r_q[active])), axis=1)
        jac = np.concatenate((dp, scale * dr), axis=1)  # (P, 7, 2)
        h = np.einsum("pki,pkj->pij", jac, jac)
        g = np.einsum("pki,pk->pi", jac, res)
        new = _qp_triangle(uv[active], h, g)
        new, at = _backtrack(model, cost, pair, active, uv[active], new, at, tolerance)
        moved = np.abs(new - uv[active]).max(axis=1) > tolerance
        uv[active] = new
        active = active[moved]
        at = tuple(a[moved] for a in at)


#: Halvings of a Gauss-Newton step that does not bring the surface nearer.
_HALVINGS = 12


def _backtrack(
    model: Callable[[np.ndarray, np.ndarray], tuple[np.ndarray, ...]],
    cost: Callable[[np.ndarray, np.ndarray, np.ndarray], np.ndarray],
    pair: np.ndarray,
    rows: np.ndarray,
    uv: np.ndarray,
    new: np.ndarray,
    at: tuple[np.ndarray, ...],
    tolerance: float,
) -> tuple[np.ndarray, tuple[np.ndarray, ...]]:
    """The step ``uv -> new`` halved until the surface point is no farther than now.

    ``at`` is the surface at ``uv`` (``model``'s four arrays); returns the
    points reached and the surface there.

    Far from a triangle its points are all about as far, and the Gauss-Newton
    model (which leaves out the residual times the surface's curvature)
    overshoots, to a corner farther than the start; a halved step along the
    same direction stays inside the triangle (it is convex). A step that no
    halving makes descend is not taken, so a projection never ends farther
    than where it started.
    """
    now = cost(rows, at[0], at[1])
    out = new.copy()
    there = tuple(a.copy() for a in at)
    t = np.ones(len(uv))
    todo = np.arange(len(uv))
    for _ in range(_HALVINGS + 1):
        trial = model(pair[rows[todo]], out[todo])
        for whole, part in zip(there, trial, strict=True):
            whole[todo] = part
        worse = cost(rows[todo], trial[0], trial[1]) > now[todo]
        todo = todo[worse]
        # a step already below the tolerance is not halved further (near the
        # minimum its cost differs from the current one by rounding only)
        t[todo] *= 0.5
        step = t[todo, None] * (new[todo] - uv[todo])
        tiny = np.abs(step).max(axis=1) <= tolerance
        stay, todo = todo[tiny], todo[~tiny]
        out[stay] = uv[stay]
        for whole, part in zip(there, at, strict=True):
            whole[stay] = part[stay]
        if not todo.size:
            return out, there
        out[todo] = uv[todo] + step[~tiny]
    out[todo] = uv[todo]
    for whole, part in zip(there, at, strict=True):
        whole[todo] = part[todo]
    return out, there


def _snap(w: np.ndarray, eps: float = 1e-12) -> np.ndarray:
    """Weights within ``eps`` of 0 or 1 set exactly (vertices and edges come out exact)."""
    w = np.where(w < eps, 0.0, w)
    w = np.where(w > 1.0 - eps, 1.0, w)
    return w / w.sum(axis=1, keepdims=True)
