"""Numba definitions of the compiled kernels (see :mod:`gcm_pipeline.robot.kernels`).

Imported by :func:`gcm_pipeline.robot.kernels.get` only, never at package import:
importing this module imports Numba and compiles every kernel for its one
signature (or loads the machine code an earlier process left in Numba's cache).
``fastmath`` stays off, so LLVM does not contract ``a * b + c`` into an FMA by
itself: the only FMAs are the explicit :func:`_fma` calls.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
from llvmlite import ir
from numba import njit, types
from numba.core import cgutils
from numba.extending import intrinsic

# C-contiguous arrays: inputs read-only (so that read-only arrays are taken
# too), the results writable
_F1 = types.Array(types.float64, 1, "C", readonly=True)
_F2 = types.Array(types.float64, 2, "C", readonly=True)
_F3 = types.Array(types.float64, 3, "C", readonly=True)
_F4 = types.Array(types.float64, 4, "C", readonly=True)
_I1 = types.Array(types.intp, 1, "C", readonly=True)


def _fma_typer(typingctx: Any, a: Any, b: Any, c: Any) -> Any:
    """``a * b + c`` with one rounding (``llvm.fma.f64``), for float64 arguments."""
    sig = types.float64(types.float64, types.float64, types.float64)

    def codegen(context: Any, builder: Any, signature: Any, args: Any) -> Any:
        d = ir.DoubleType()
        fn = cgutils.get_or_insert_function(
            builder.module, ir.FunctionType(d, [d, d, d]), "llvm.fma.f64"
        )
        return builder.call(fn, args)

    return sig, codegen


#: ``_fma(a, b, c)``: ``a * b + c`` with one rounding, in compiled code.
_fma: Any = intrinsic(_fma_typer)


@njit(cache=True, inline="always")
def _dot4(a: Any, r: int, b: Any, c: int) -> float:
    """``(a @ b)[r, c]`` of a (3, 4) and a (4, 4) matrix, summed as OpenBLAS's dgemm does.

    Its Haswell/Zen kernel sums ``k = 0..3`` as one FMA chain:
    ``fma(a3, b3, fma(a2, b2, fma(a1, b1, a0 * b0)))``.
    """
    acc = a[r, 0] * b[0, c]
    acc = _fma(a[r, 1], b[1, c], acc)
    acc = _fma(a[r, 2], b[2, c], acc)
    return _fma(a[r, 3], b[3, c], acc)


@njit(
    types.Tuple((types.float64[:, :, ::1], types.float64[:, ::1], types.float64[:, :, ::1]))(
        _F2, _I1, _F3, _F2, types.intp, types.boolean
    ),
    cache=True,
)
def chain_forward(q, q_index, placement, tool, nq, jacobian):
    """:meth:`~gcm_pipeline.robot.chain.KinematicChain._forward`, one configuration at a time.

    Each joint's frame is its parent's times its placement, then turned about
    z by ``q``: the x and y columns times ``exp(-i q)`` as a complex product,
    ``re = fma(x, c, -(y s))``, ``im = fma(x, s, y c)`` (NumPy's AVX2 loop).

    Args:
        q: Configurations (N, nq') [rad].
        q_index: Column of ``q`` of each joint of the chain (nj,).
        placement: Joint placements (nj, 4, 4), axes turned onto z.
        tool: The frame's placement on the last joint (4, 4).
        nq: Columns of the Jacobian.
        jacobian: Whether to compute the Jacobian.

    Returns:
        Rotations (N, 3, 3), positions (N, 3) and Jacobians (N, 6, nq), zero in
        the columns of joints outside the chain ((0, 6, nq) without ``jacobian``).
    """
    n = q.shape[0]
    nj = q_index.shape[0]
    rot = np.empty((n, 3, 3))
    pos = np.empty((n, 3))
    jac = np.zeros((n if jacobian else 0, 6, nq))
    frame = np.empty((nj, 3, 4))
    tcp = np.empty((3, 4))
    for i in range(n):
        for k in range(nj):
            angle = q[i, q_index[k]]
            c = math.cos(angle)  # exp(-i q) = cos(q) - i sin(q)
            s = -math.sin(angle)
            f = frame[k]
            for r in range(3):
                if k == 0:
                    for col in range(4):
                        f[r, col] = placement[0, r, col]
                else:
                    for col in range(4):
                        f[r, col] = _dot4(frame[k - 1], r, placement[k], col)
                x = f[r, 0]
                y = f[r, 1]
                f[r, 0] = _fma(x, c, -(y * s))
                f[r, 1] = _fma(x, s, y * c)
        for r in range(3):
            for col in range(4):
                tcp[r, col] = _dot4(frame[nj - 1], r, tool, col) if nj else tool[r, col]
            for col in range(3):
                rot[i, r, col] = tcp[r, col]
            pos[i, r] = tcp[r, 3]
        if not jacobian:
            continue
        for k in range(nj):
            f = frame[k]
            # linear: z x (p_tool - p_joint); angular: z
            d0 = tcp[0, 3] - f[0, 3]
            d1 = tcp[1, 3] - f[1, 3]
            d2 = tcp[2, 3] - f[2, 3]
            j = q_index[k]
            jac[i, 0, j] = f[1, 2] * d2 - f[2, 2] * d1
            jac[i, 1, j] = f[2, 2] * d0 - f[0, 2] * d2
            jac[i, 2, j] = f[0, 2] * d1 - f[1, 2] * d0
            jac[i, 3, j] = f[0, 2]
            jac[i, 4, j] = f[1, 2]
            jac[i, 5, j] = f[2, 2]
    return rot, pos, jac


@njit(cache=True, inline="always")
def _place(tf: Any, centre: Any, out: Any) -> None:
    """``out`` (3,) = the point ``centre`` (3,) fixed to a joint whose frame is ``tf`` (3, 4)."""
    for r in range(3):
        out[r] = tf[r, 0] * centre[0] + tf[r, 1] * centre[1] + tf[r, 2] * centre[2] + tf[r, 3]


@njit(cache=True, inline="always")
def _lower(p: Any, shape: Any) -> float:
    """Lower bound of the distance from point ``p`` (3,) to a world shape (a packed row).

    The row is ``_ShapeBound.packed`` (:mod:`gcm_pipeline.robot.collision`): the
    shape's inverse placement's first three rows (12), its kind, radius, half
    length, box centre (3), half sizes (3). The same bound as ``_ShapeBound.lower``.
    """
    x = shape[0] * p[0] + shape[1] * p[1] + shape[2] * p[2] + shape[3]
    y = shape[4] * p[0] + shape[5] * p[1] + shape[6] * p[2] + shape[7]
    z = shape[8] * p[0] + shape[9] * p[1] + shape[10] * p[2] + shape[11]
    kind = int(shape[12])
    if kind == 0:  # sphere
        return max(math.sqrt(x * x + y * y + z * z) - shape[13], 0.0)
    if kind == 1:  # cylinder
        radial = max(math.sqrt(x * x + y * y) - shape[13], 0.0)
        axial = max(abs(z) - shape[14], 0.0)
        return math.sqrt(radial * radial + axial * axial)
    if kind == 2:  # capsule
        along = z - min(max(z, -shape[14]), shape[14])
        return max(math.sqrt(x * x + y * y + along * along) - shape[13], 0.0)
    bx = max(abs(x - shape[15]) - shape[18], 0.0)  # box
    by = max(abs(y - shape[16]) - shape[19], 0.0)
    bz = max(abs(z - shape[17]) - shape[20], 0.0)
    return math.sqrt(bx * bx + by * by + bz * bz)


@njit(cache=True, inline="always")
def _sq_gap(a: Any, b: Any) -> float:
    """Squared distance of two points (3,)."""
    d0 = a[0] - b[0]
    d1 = a[1] - b[1]
    d2 = a[2] - b[2]
    return d0 * d0 + d1 * d1 + d2 * d2


@njit(
    types.boolean[:, ::1](
        _F4, _I1, _F2, _I1, _F2, _I1, _I1, _I1, _F1, _I1, _I1, _I1, _I1, _F1, _F2
    ),
    cache=True,
)
def broad_phase(
    tfs,
    ball_joint,
    ball_centre,
    sphere_joint,
    sphere_centre,
    geom_a,
    geom_b,
    world,
    limit1,
    first_test,
    n_tests,
    sphere_a,
    sphere_b,
    limit2,
    shapes,
):
    """Levels 1 and 2 of the broad phase: the (pair, configuration) entries left open.

    Pair ``k`` is a self pair when ``world[k] < 0`` (geometries ``geom_a[k]``
    and ``geom_b[k]``), else geometry ``geom_a[k]`` against the world shape
    ``shapes[world[k]]``. It stays open in a configuration when (1) its
    bounding spheres are within reach, ``|ca - cb|^2 <= limit1[k]`` (self) or
    ``lower(ca) <= limit1[k]`` (world), and (2) one of its sphere tests
    ``e = first_test[k] .. first_test[k] + n_tests[k] - 1`` is within reach:
    ``|pa - pb|^2 <= limit2[e]`` or ``lower(pa) <= limit2[e]``. The limits
    hold the radii, the margin and the slack.

    Args:
        tfs: Joint frames (J, N, 3, 4).
        ball_joint: Joint of each geometry's bounding sphere (G,).
        ball_centre: Their centres in the joints' frames (G, 3) [m].
        sphere_joint: Joint of each cover sphere (S,).
        sphere_centre: Their centres in the joints' frames (S, 3) [m].
        geom_a: Robot geometry of each pair (P,).
        geom_b: The other robot geometry of a self pair (P,).
        world: Row of ``shapes`` of a world pair, -1 for a self pair (P,).
        limit1: Level-1 limit of each pair (P,).
        first_test: First sphere test of each pair (P,).
        n_tests: Number of sphere tests of each pair (P,).
        sphere_a: Robot-side cover sphere of each test (E,).
        sphere_b: Other cover sphere of a self pair's test (E,).
        limit2: Level-2 limit of each test (E,).
        shapes: World shapes as packed rows (W, 21) (see :func:`_lower`).

    Returns:
        (P, N) bool: True where the pair is left open.
    """
    n = tfs.shape[1]
    npairs = geom_a.shape[0]
    open_ = np.zeros((npairs, n), dtype=np.bool_)
    ball = np.empty((ball_joint.shape[0], 3))
    sphere = np.empty((sphere_joint.shape[0], 3))
    for i in range(n):
        for g in range(ball_joint.shape[0]):
            _place(tfs[ball_joint[g], i], ball_centre[g], ball[g])
        placed = False
        for k in range(npairs):
            w = world[k]
            # 1. one bounding sphere per geometry
            if w < 0:
                if _sq_gap(ball[geom_a[k]], ball[geom_b[k]]) > limit1[k]:
                    continue
            elif _lower(ball[geom_a[k]], shapes[w]) > limit1[k]:
                continue
            # 2. the sphere covers (all placed once per configuration, when first needed)
            if not placed:
                for e in range(sphere_joint.shape[0]):
                    _place(tfs[sphere_joint[e], i], sphere_centre[e], sphere[e])
                placed = True
            for e in range(first_test[k], first_test[k] + n_tests[k]):
                if w < 0:
                    near = _sq_gap(sphere[sphere_a[e]], sphere[sphere_b[e]]) <= limit2[e]
                else:
                    near = _lower(sphere[sphere_a[e]], shapes[w]) <= limit2[e]
                if near:
                    open_[k, i] = True
                    break
    return open_


@njit(types.int8[::1](_F3, _I1, _F2, _F2, _F1, _F1), cache=True)
def hull_vs_box(tfs, rows, verts, inv, beyond, deep):
    """Level 3 of the broad phase: a robot polytope's hull vertices against a box.

    In the box's frame, ``x = inv @ T @ [v; 1]`` for each hull vertex ``v``.

    Args:
        tfs: Frames of the polytope's joint (N, 3, 4).
        rows: Configurations to decide (M,).
        verts: Hull vertices (3, V) in the joint's frame [m].
        inv: The box's inverse placement (4, 4).
        beyond: Free when, along one axis ``a``, every vertex has
            ``x_a > beyond[a]`` or every vertex ``x_a < -beyond[a]`` (3,).
        deep: Collides when a vertex has ``|x_a| < deep[a]`` on all three axes (3,).

    Returns:
        (M,) int8: 0 free, 1 collides, 2 undecided.
    """
    m = rows.shape[0]
    out = np.empty(m, dtype=np.int8)
    rot = np.empty((3, 3))
    off = np.empty(3)
    x = np.empty(3)
    for r in range(m):
        tf = tfs[rows[r]]
        for a in range(3):
            for b in range(4):
                v = inv[a, 0] * tf[0, b] + inv[a, 1] * tf[1, b] + inv[a, 2] * tf[2, b]
                if b < 3:
                    rot[a, b] = v
                else:
                    off[a] = v + inv[a, 3]
        above0 = above1 = above2 = below0 = below1 = below2 = True
        inside = False
        for v in range(verts.shape[1]):
            for a in range(3):
                x[a] = rot[a, 0] * verts[0, v] + rot[a, 1] * verts[1, v]
                x[a] += rot[a, 2] * verts[2, v] + off[a]
            above0 = above0 and x[0] > beyond[0]
            below0 = below0 and x[0] < -beyond[0]
            above1 = above1 and x[1] > beyond[1]
            below1 = below1 and x[1] < -beyond[1]
            above2 = above2 and x[2] > beyond[2]
            below2 = below2 and x[2] < -beyond[2]
            if abs(x[0]) < deep[0] and abs(x[1]) < deep[1] and abs(x[2]) < deep[2]:
                inside = True
                break
        if inside:
            out[r] = 1
        elif above0 or below0 or above1 or below1 or above2 or below2:
            out[r] = 0
        else:
            out[r] = 2
    return out
