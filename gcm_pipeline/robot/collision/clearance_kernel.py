"""Compiled kernels of the clearance (distances of the robot to the world).

Kernels of :class:`~gcm_pipeline.robot.collision.clearance.ClearanceQueries` (the NumPy
reference, beside this module), one configuration at a time:
:func:`sphere_bounds` (the pairs' lower bounds from the sphere covers, as
``ShapeBound.lower`` minus the radius, the minimum over each pair's spheres),
:func:`face_distances` (exact distances of a robot polytope in the region of one face
of a box) and :func:`vertex_distances` (a polytope's nearest hull vertex and the
separating plane through the shape's nearest point). The same arithmetic as the
NumPy code, summed in another order: equal to round-off (the tests compare to
1e-12 m). Imported by :func:`gcm_pipeline.robot.kernels.get` only (it imports Numba).
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
from numba import njit, types

from gcm_pipeline.robot.collision.broadphase_kernel import _lower, _place
from gcm_pipeline.robot.kernel_common import F1, F2, F4, I1

B2 = types.Array(types.boolean, 2, "C", readonly=True)


@njit(types.float64[:, ::1](F4, I1, F2, F1, I1, I1, I1, F2), cache=True)
def sphere_bounds(tfs, sphere_joint, sphere_centre, radius, start, owner, world, shapes):
    """Lower bounds (N, P) of the clearance pairs' distances from the sphere covers.

    Args:
        tfs: Every joint's frame (J, N, 3, 4).
        sphere_joint: Joint of each cover sphere (S,).
        sphere_centre: Their centres in the joints' frames (S, 3).
        radius: Their radii (S,).
        start: Geometry g's spheres are ``start[g] .. start[g + 1] - 1`` (R + 1,).
        owner: Each pair's robot geometry (P,).
        world: Each pair's row of ``shapes`` (P,).
        shapes: World shapes as packed rows (W, 21) (``ShapeBound.packed``).
    """
    n = tfs.shape[1]
    npair = owner.shape[0]
    out = np.empty((n, npair))
    placed = np.empty((sphere_joint.shape[0], 3))
    for i in range(n):
        for e in range(sphere_joint.shape[0]):
            _place(tfs[sphere_joint[e], i], sphere_centre[e], placed[e])
        for p in range(npair):
            g = owner[p]
            shape = shapes[world[p]]
            best = np.inf
            for e in range(start[g], start[g + 1]):
                d = _lower(placed[e], shape) - radius[e]
                if d < best:
                    best = d
            out[i, p] = best
    return out


@njit(cache=True, inline="always")
def _face_height(tf: Any, inv: Any, verts: Any, v0: int, v1: int, axis: int, sign: float) -> float:
    """Height of the lowest hull vertex ``v0 .. v1 - 1`` over a box's mid-plane along ``axis``."""
    n0, n1, n2 = sign * inv[axis, 0], sign * inv[axis, 1], sign * inv[axis, 2]
    w0 = n0 * tf[0, 0] + n1 * tf[1, 0] + n2 * tf[2, 0]  # R^T u
    w1 = n0 * tf[0, 1] + n1 * tf[1, 1] + n2 * tf[2, 1]
    w2 = n0 * tf[0, 2] + n1 * tf[1, 2] + n2 * tf[2, 2]
    low = np.inf
    for v in range(v0, v1):
        h = w0 * verts[v, 0] + w1 * verts[v, 1] + w2 * verts[v, 2]
        if h < low:
            low = h
    return low + (n0 * tf[0, 3] + n1 * tf[1, 3] + n2 * tf[2, 3]) + sign * inv[axis, 3]


@njit(types.float64[:, ::1](F4, I1, F2, F1, I1, I1, I1, I1, F2, I1, F2, F2, F2), cache=True)
def face_distances(
    tfs,
    sphere_joint,
    sphere_centre,
    radius,
    start,
    hull_joint,
    order,
    geom,
    invs,
    vstart,
    verts,
    halfs,
    bound,
):
    """Exact distances (N, P) of robot polytopes to boxes in one face's region, NaN elsewhere.

    ``ClearanceQueries._face_distances``, one configuration at a time.

    Args:
        tfs: Every joint's frame (J, N, 3, 4).
        sphere_joint: Joint of each cover sphere (S,).
        sphere_centre: The cover spheres' centres in their joints' frames (S, 3).
        radius: Their radii (S,).
        start: Geometry g's spheres are ``start[g] .. start[g + 1] - 1`` (R + 1,).
        hull_joint: The joint of each box pair's hull vertices (B,).
        order: The box pairs' columns in the order they are visited (B,).
        geom: Their robot geometries (B,).
        invs: The boxes' inverse placements' first three rows, (B, 12).
        vstart: Box pair b's hull vertices are ``vstart[b] .. vstart[b + 1] - 1`` (B + 1,).
        verts: The hull vertices in their joint's frame (V, 3).
        halfs: The boxes' half sizes (B, 3).
        bound: The pairs' lower bounds (N, P): pairs no nearer than a distance
            found are left out.
    """
    n, npair = bound.shape
    out = np.full((n, npair), np.nan)
    c = np.empty(3)
    inv = np.empty((3, 4))
    for i in range(n):
        best = np.inf
        for b in range(order.shape[0]):
            col = order[b]
            if not bound[i, col] < best:
                continue
            g = geom[b]
            for r in range(3):
                for k in range(4):
                    inv[r, k] = invs[b, 4 * r + k]
            hx, hy, hz = halfs[b, 0], halfs[b, 1], halfs[b, 2]
            # lateral per axis: every sphere within the box across the other two axes
            in0, in1, in2 = True, True, True
            f0, f1, f2 = 0.0, 0.0, 0.0  # the first sphere's centre in the box's frame
            for e in range(start[g], start[g + 1]):
                _place(tfs[sphere_joint[e], i], sphere_centre[e], c)
                x = inv[0, 0] * c[0] + inv[0, 1] * c[1] + inv[0, 2] * c[2] + inv[0, 3]
                y = inv[1, 0] * c[0] + inv[1, 1] * c[1] + inv[1, 2] * c[2] + inv[1, 3]
                z = inv[2, 0] * c[0] + inv[2, 1] * c[1] + inv[2, 2] * c[2] + inv[2, 3]
                if e == start[g]:
                    f0, f1, f2 = x, y, z
                rad = radius[e]
                ax, ay, az = abs(x) + rad, abs(y) + rad, abs(z) + rad
                in0 = in0 and ay <= hy and az <= hz
                in1 = in1 and ax <= hx and az <= hz
                in2 = in2 and ax <= hx and ay <= hy
            tf = tfs[hull_joint[b], i]
            for axis in range(3):
                lateral = in0 if axis == 0 else (in1 if axis == 1 else in2)
                if not lateral:
                    continue
                first = f0 if axis == 0 else (f1 if axis == 1 else f2)
                sign = 1.0 if first >= 0 else -1.0
                height = _face_height(tf, inv, verts, vstart[b], vstart[b + 1], axis, sign)
                height -= halfs[b, axis]
                if height >= 0:
                    out[i, col] = height
                    if height < best:
                        best = height
    return out


@njit(cache=True, inline="always")
def _nearest(p: Any, shape: Any, out: Any) -> None:
    """``out`` (3,): the nearest point of a primitive to ``p`` (3,) in its frame (``nearest``)."""
    kind = int(shape[12])
    radius, half = shape[13], shape[14]
    if kind == 0:  # sphere
        norm = math.sqrt(p[0] * p[0] + p[1] * p[1] + p[2] * p[2])
        s = radius / max(norm, 1e-300) if norm > radius else 1.0
        out[0], out[1], out[2] = p[0] * s, p[1] * s, p[2] * s
    elif kind == 1:  # cylinder
        radial = math.sqrt(p[0] * p[0] + p[1] * p[1])
        s = min(1.0, radius / max(radial, 1e-300))
        out[0], out[1] = p[0] * s, p[1] * s
        out[2] = min(max(p[2], -half), half)
    elif kind == 2:  # capsule
        z = min(max(p[2], -half), half)
        r2 = p[2] - z
        norm = math.sqrt(p[0] * p[0] + p[1] * p[1] + r2 * r2)
        s = radius / max(norm, 1e-300) if norm > radius else 1.0
        out[0], out[1], out[2] = p[0] * s, p[1] * s, z + r2 * s
    else:  # box
        for r in range(3):
            out[r] = shape[15 + r] + min(max(p[r] - shape[15 + r], -shape[18 + r]), shape[18 + r])


@njit(cache=True, inline="always")
def _support(n: Any, shape: Any) -> float:
    """The support function ``max n . x`` of a primitive in its frame (``support``)."""
    kind = int(shape[12])
    radius, half = shape[13], shape[14]
    if kind == 0:
        return radius * math.sqrt(n[0] * n[0] + n[1] * n[1] + n[2] * n[2])
    if kind == 1:
        return radius * math.sqrt(n[0] * n[0] + n[1] * n[1]) + half * abs(n[2])
    if kind == 2:
        return radius * math.sqrt(n[0] * n[0] + n[1] * n[1] + n[2] * n[2]) + half * abs(n[2])
    s = n[0] * shape[15] + n[1] * shape[16] + n[2] * shape[17]
    return s + (abs(n[0]) * shape[18] + abs(n[1]) * shape[19] + abs(n[2]) * shape[20])


@njit(
    types.UniTuple(types.float64[:, ::1], 2)(F4, B2, I1, I1, I1, F2, F2, types.float64),
    cache=True,
)
def vertex_distances(tfs, need, pair_joint, pair_shape, vstart, verts, shapes, precision):
    """Bounds ``(U, L)`` (N, P) of the pairs ``need`` (N, P) from hull vertices, NaN elsewhere.

    ``ClearanceQueries._vertex_distances``, one configuration at a time.

    Args:
        tfs: Every joint's frame (J, N, 3, 4).
        need: The (configuration, pair) entries to bound.
        pair_joint: Each pair's robot joint, -1 for a pair without vertex bounds (P,).
        pair_shape: Each pair's row of ``shapes`` (P,).
        vstart: Pair p's hull vertices are ``vstart[p] .. vstart[p + 1] - 1`` (P + 1,).
        verts: The hull vertices in their joint's frame (V, 3).
        shapes: The world primitives as packed rows (W, 21).
        precision: Bounds are kept where ``U - L <= precision``.
    """
    n, npair = need.shape
    upper = np.full((n, npair), np.nan)
    lower = np.full((n, npair), np.nan)
    pts = np.empty((max(verts.shape[0], 1), 3))
    near = np.empty(3)
    gap = np.empty(3)
    rot = np.empty((3, 4))  # the joint's frame in the shape's frame: [inv R | inv p + t]
    for i in range(n):
        for p in range(npair):
            if not need[i, p] or pair_joint[p] < 0:
                continue
            tf = tfs[pair_joint[p], i]
            s = shapes[pair_shape[p]]
            for r in range(3):
                for c in range(4):
                    rot[r, c] = (
                        s[4 * r] * tf[0, c] + s[4 * r + 1] * tf[1, c] + s[4 * r + 2] * tf[2, c]
                    )
                rot[r, 3] += s[4 * r + 3]
            v0, nv = vstart[p], vstart[p + 1] - vstart[p]
            best = np.inf
            for k in range(nv):
                x = verts[v0 + k]
                for r in range(3):
                    pts[k, r] = rot[r, 0] * x[0] + rot[r, 1] * x[1] + rot[r, 2] * x[2] + rot[r, 3]
                _nearest(pts[k], s, near)
                d0, d1, d2 = pts[k, 0] - near[0], pts[k, 1] - near[1], pts[k, 2] - near[2]
                d = math.sqrt(d0 * d0 + d1 * d1 + d2 * d2)
                if d < best:
                    best = d
                    gap[0], gap[1], gap[2] = d0, d1, d2
            if not best > 0:
                continue
            n0, n1, n2 = gap[0] / best, gap[1] / best, gap[2] / best
            low = np.inf
            for k in range(nv):
                h = pts[k, 0] * n0 + pts[k, 1] * n1 + pts[k, 2] * n2
                if h < low:
                    low = h
            gap[0], gap[1], gap[2] = n0, n1, n2
            low -= _support(gap, s)
            if best - low <= precision:
                upper[i, p] = best
                lower[i, p] = low
    return upper, lower
