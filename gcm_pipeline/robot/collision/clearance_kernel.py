"""Compiled kernels of the clearance (distances of the robot to the world).

Kernels of :class:`~gcm_pipeline.robot.collision.clearance.ClearanceQueries` (the NumPy
reference, beside this module), one configuration at a time (the sphere bounds
:data:`CHUNK` at a time): :func:`sphere_bounds` (the pairs' lower bounds from the sphere covers, as
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

from gcm_pipeline.robot.collision.broadphase_kernel import (
    _place,
    _place_balls,
    _point_bound,
    _shape_numbers,
)
from gcm_pipeline.robot.kernel_common import F1, F2, F4, I1

B2 = types.Array(types.boolean, 2, "C", readonly=True)


#: Configurations whose sphere bounds are computed together, sphere by sphere (a
#: loop LLVM vectorises; their spheres' centres stay in the L1 cache).
CHUNK = 64


@njit(cache=True, inline="always")
def _min_bound(a: Any, m: int, s: Any, radius: float, best: Any) -> None:
    """``best[i] = min(best[i], lower(a[:, i]) - radius)`` for points ``a`` (3, m).

    ``ShapeBound.lower`` of the packed shape row ``s``, its numbers read once, as
    ``broadphase_kernel._world_level1``.
    """
    shape = _shape_numbers(s)
    for i in range(m):
        best[i] = min(best[i], _point_bound(a[0, i], a[1, i], a[2, i], shape) - radius)


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
    placed = np.empty((sphere_joint.shape[0], 3, CHUNK))
    best = np.empty(CHUNK)
    for i0 in range(0, n, CHUNK):
        m = min(CHUNK, n - i0)
        _place_balls(tfs, i0, m, sphere_joint, sphere_centre, placed)
        for p in range(npair):
            g = owner[p]
            shape = shapes[world[p]]
            best[:] = np.inf
            for e in range(start[g], start[g + 1]):
                _min_bound(placed[e], m, shape, radius[e], best)
            for i in range(m):
                out[i0 + i, p] = best[i]
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


@njit(cache=True, inline="always")
def _gap_lengths(s: Any, pts: Any, nv: int, dist: Any) -> None:
    """``dist[k]``: the distance of point ``pts[:, k]`` (3, nv) from a primitive (packed row).

    ``|p - nearest(p)|`` as :func:`_nearest` computes it, one loop per kind with the
    shape's numbers read once (a loop LLVM vectorises).
    """
    kind = int(s[12])
    radius, half = s[13], s[14]
    px, py, pz = pts[0], pts[1], pts[2]
    if kind == 1:  # cylinder
        for k in range(nv):
            x, y, z = px[k], py[k], pz[k]
            f = min(1.0, radius / max(math.sqrt(x * x + y * y), 1e-300))
            gx, gy, gz = x - x * f, y - y * f, z - min(max(z, -half), half)
            dist[k] = math.sqrt(gx * gx + gy * gy + gz * gz)
    elif kind == 3:  # box
        cx, cy, cz, hx, hy, hz = s[15], s[16], s[17], s[18], s[19], s[20]
        for k in range(nv):
            gx = px[k] - (cx + min(max(px[k] - cx, -hx), hx))
            gy = py[k] - (cy + min(max(py[k] - cy, -hy), hy))
            gz = pz[k] - (cz + min(max(pz[k] - cz, -hz), hz))
            dist[k] = math.sqrt(gx * gx + gy * gy + gz * gz)
    else:  # sphere, capsule: about a point of the axis
        for k in range(nv):
            x, y = px[k], py[k]
            a = min(max(pz[k], -half), half) if kind == 2 else 0.0
            z = pz[k] - a
            norm = math.sqrt(x * x + y * y + z * z)
            f = radius / max(norm, 1e-300) if norm > radius else 1.0
            gx, gy, gz = x - x * f, y - y * f, z - z * f
            dist[k] = math.sqrt(gx * gx + gy * gy + gz * gz)


@njit(cache=True, inline="always")
def _vertex_bounds(tf: Any, s: Any, verts: Any, v0: int, nv: int, work: Any, pts: Any) -> Any:
    """``(U, L)`` of one pair: its nearest hull vertex's distance, the separating plane's.

    ``work`` (5, 4) and ``pts`` (4, nv) are scratch space (no allocation per pair).
    """
    rot = work[:3]  # the joint's frame in the shape's frame: [inv R | inv p + t]
    dist = pts[3]
    for r in range(3):
        for c in range(4):
            rot[r, c] = s[4 * r] * tf[0, c] + s[4 * r + 1] * tf[1, c] + s[4 * r + 2] * tf[2, c]
        rot[r, 3] += s[4 * r + 3]
    for r in range(3):
        r0, r1, r2, r3 = rot[r, 0], rot[r, 1], rot[r, 2], rot[r, 3]
        out = pts[r]
        for k in range(nv):
            out[k] = r0 * verts[0, v0 + k] + r1 * verts[1, v0 + k] + r2 * verts[2, v0 + k] + r3
    _gap_lengths(s, pts, nv, dist)
    best, at = np.inf, 0
    for k in range(nv):
        if dist[k] < best:
            best, at = dist[k], k
    if not best > 0:
        return best, np.nan
    p, near = work[3], work[4]
    for r in range(3):
        p[r] = pts[r, at]
    _nearest(p, s, near)
    for r in range(3):
        near[r] = (p[r] - near[r]) / best  # the normal
    low = np.inf
    for k in range(nv):
        h = pts[0, k] * near[0] + pts[1, k] * near[1] + pts[2, k] * near[2]
        low = min(low, h)
    return best, low - _support(near, s)


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
        verts: The hull vertices in their joint's frame, coordinates first (3, V).
        shapes: The world primitives as packed rows (W, 21).
        precision: Bounds are kept where ``U - L <= precision``.
    """
    n, npair = need.shape
    upper = np.full((n, npair), np.nan)
    lower = np.full((n, npair), np.nan)
    size = 1
    for p in range(npair):
        size = max(size, vstart[p + 1] - vstart[p])
    work = np.empty((5, 4))
    pts = np.empty((4, size))
    for i in range(n):
        for p in range(npair):
            if not need[i, p] or pair_joint[p] < 0:
                continue
            tf = tfs[pair_joint[p], i]
            s = shapes[pair_shape[p]]
            v0, nv = vstart[p], vstart[p + 1] - vstart[p]
            best, low = _vertex_bounds(tf, s, verts, v0, nv, work, pts)
            if best > 0 and best - low <= precision:
                upper[i, p] = best
                lower[i, p] = low
    return upper, lower
