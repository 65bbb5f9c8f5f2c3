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
_I1W = types.intp[::1]


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


@njit(cache=True, inline="always")
def _frames(turn: Any, placement: Any, tool: Any, frame: Any, tcp: Any) -> None:
    """Every joint's frame and the tool frame of one configuration of a chain, in place.

    Each joint's frame is its parent's times its placement, then turned about
    z by its angle q: the x and y columns times ``exp(-i q)`` as a complex
    product, ``re = fma(x, c, -(y s))``, ``im = fma(x, s, y c)`` with
    ``c = cos q``, ``s = -sin q`` (NumPy's AVX2 loop).

    Args:
        turn: ``(cos q, sin q)`` of each joint of the chain (nj, 2).
        placement: Joint placements (nj, 4, 4), axes turned onto z.
        tool: The frame's placement on the last joint (4, 4).
        frame: Out: the joints' frames (nj, 3, 4).
        tcp: Out: the tool frame (3, 4).
    """
    nj = turn.shape[0]
    for k in range(nj):
        c = turn[k, 0]
        s = -turn[k, 1]
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


@njit(cache=True, inline="always")
def _columns(frame: Any, tcp: Any, jac: Any) -> None:
    """Jacobian columns (6, nj) in chain order: linear ``z x (p_tool - p_joint)``, angular ``z``."""
    for k in range(frame.shape[0]):
        f = frame[k]
        d0 = tcp[0, 3] - f[0, 3]
        d1 = tcp[1, 3] - f[1, 3]
        d2 = tcp[2, 3] - f[2, 3]
        jac[0, k] = f[1, 2] * d2 - f[2, 2] * d1
        jac[1, k] = f[2, 2] * d0 - f[0, 2] * d2
        jac[2, k] = f[0, 2] * d1 - f[1, 2] * d0
        jac[3, k] = f[0, 2]
        jac[4, k] = f[1, 2]
        jac[5, k] = f[2, 2]


@njit(
    types.Tuple((types.float64[:, :, ::1], types.float64[:, ::1], types.float64[:, :, ::1]))(
        _F2, _I1, _F3, _F2, types.intp, types.boolean
    ),
    cache=True,
)
def chain_forward(q, q_index, placement, tool, nq, jacobian):
    """:meth:`~gcm_pipeline.robot.chain.KinematicChain._forward`, one configuration at a time.

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
    turn = np.empty((nj, 2))
    columns = np.empty((6, nj))
    for i in range(n):
        for k in range(nj):
            turn[k, 0] = math.cos(q[i, q_index[k]])
            turn[k, 1] = math.sin(q[i, q_index[k]])
        _frames(turn, placement, tool, frame, tcp)
        for r in range(3):
            for col in range(3):
                rot[i, r, col] = tcp[r, col]
            pos[i, r] = tcp[r, 3]
        if not jacobian:
            continue
        _columns(frame, tcp, columns)
        for k in range(nj):
            for a in range(6):
                jac[i, a, q_index[k]] = columns[a, k]
    return rot, pos, jac


@njit(cache=True, inline="always")
def _place(tf: Any, centre: Any, out: Any) -> None:
    """``out`` (3,) = the point ``centre`` (3,) fixed to a joint whose frame is ``tf`` (3, 4)."""
    for r in range(3):
        out[r] = tf[r, 0] * centre[0] + tf[r, 1] * centre[1] + tf[r, 2] * centre[2] + tf[r, 3]


@njit(cache=True, inline="always")
def _lower(p: Any, shape: Any) -> float:
    """Lower bound of the distance from point ``p`` (3,) to a world shape (a packed row).

    The row is ``ShapeBound.packed`` (:mod:`gcm_pipeline.robot.collision.broadphase`): the
    shape's inverse placement's first three rows (12), its kind, radius, half
    length, box centre (3), half sizes (3). The same bound as ``ShapeBound.lower``.
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


@njit(cache=True)
def _solve6(a: Any, e: Any, y: Any) -> None:
    """``y = a^-1 e`` for a symmetric positive definite ``a`` (6, 6), by Cholesky (overwrites a)."""
    for j in range(6):
        s = a[j, j]
        for k in range(j):
            s -= a[j, k] * a[j, k]
        d = math.sqrt(s)
        a[j, j] = d
        for i in range(j + 1, 6):
            s = a[i, j]
            for k in range(j):
                s -= a[i, k] * a[j, k]
            a[i, j] = s / d
    for i in range(6):
        s = e[i]
        for k in range(i):
            s -= a[i, k] * y[k]
        y[i] = s / a[i, i]
    for i in range(5, -1, -1):
        s = y[i]
        for k in range(i + 1, 6):
            s -= a[k, i] * y[k]
        y[i] = s / a[i, i]


@njit(cache=True)
def _damped_step(jac: Any, e: Any, lam: float, free: Any, a: Any, y: Any, dq: Any) -> None:
    """``dq = J^T (J J^T + lam I)^-1 e`` over the columns ``free`` of ``jac`` (6, nj), else 0."""
    nj = jac.shape[1]
    for i in range(6):
        for j in range(i + 1):
            s = 0.0
            for k in range(nj):
                if free[k]:
                    s += jac[i, k] * jac[j, k]
            a[i, j] = s
            a[j, i] = s
        a[i, i] += lam
    _solve6(a, e, y)
    for k in range(nj):
        s = 0.0
        if free[k]:
            for i in range(6):
                s += jac[i, k] * y[i]
        dq[k] = s


@njit(cache=True)
def _pose_error(trot: Any, tpos: Any, tcp: Any, e: Any) -> None:
    """``e`` (6,) = (tpos - position, log3(trot @ rotation^T)) of the tool frame ``tcp`` (3, 4).

    The logarithm as :func:`~gcm_pipeline.robot.ik.lm.log3` computes it.
    """
    for i in range(3):
        e[i] = tpos[i] - tcp[i, 3]
    r00 = trot[0, 0] * tcp[0, 0] + trot[0, 1] * tcp[0, 1] + trot[0, 2] * tcp[0, 2]
    r01 = trot[0, 0] * tcp[1, 0] + trot[0, 1] * tcp[1, 1] + trot[0, 2] * tcp[1, 2]
    r02 = trot[0, 0] * tcp[2, 0] + trot[0, 1] * tcp[2, 1] + trot[0, 2] * tcp[2, 2]
    r10 = trot[1, 0] * tcp[0, 0] + trot[1, 1] * tcp[0, 1] + trot[1, 2] * tcp[0, 2]
    r11 = trot[1, 0] * tcp[1, 0] + trot[1, 1] * tcp[1, 1] + trot[1, 2] * tcp[1, 2]
    r12 = trot[1, 0] * tcp[2, 0] + trot[1, 1] * tcp[2, 1] + trot[1, 2] * tcp[2, 2]
    r20 = trot[2, 0] * tcp[0, 0] + trot[2, 1] * tcp[0, 1] + trot[2, 2] * tcp[0, 2]
    r21 = trot[2, 0] * tcp[1, 0] + trot[2, 1] * tcp[1, 1] + trot[2, 2] * tcp[1, 2]
    r22 = trot[2, 0] * tcp[2, 0] + trot[2, 1] * tcp[2, 1] + trot[2, 2] * tcp[2, 2]
    v0 = 0.5 * (r21 - r12)
    v1 = 0.5 * (r02 - r20)
    v2 = 0.5 * (r10 - r01)
    c = 0.5 * (r00 + r11 + r22 - 1.0)
    s = math.sqrt(v0 * v0 + v1 * v1 + v2 * v2)
    if s > 1e-12:
        scale = math.atan2(s, c) / s
        e[3], e[4], e[5] = v0 * scale, v1 * scale, v2 * scale
    elif c < 0:
        # a half turn: the axis is the column of (R + I) / 2 with the largest diagonal
        if r00 >= r11 and r00 >= r22:
            x0, x1, x2 = 0.5 * (r00 + 1.0), 0.5 * r10, 0.5 * r20
        elif r11 >= r22:
            x0, x1, x2 = 0.5 * r01, 0.5 * (r11 + 1.0), 0.5 * r21
        else:
            x0, x1, x2 = 0.5 * r02, 0.5 * r12, 0.5 * (r22 + 1.0)
        norm = math.sqrt(x0 * x0 + x1 * x1 + x2 * x2)
        e[3], e[4], e[5] = math.pi * x0 / norm, math.pi * x1 / norm, math.pi * x2 / norm
    else:
        e[3], e[4], e[5] = v0, v1, v2


@njit(
    types.Tuple(
        (types.float64[:, ::1], types.boolean[::1], types.float64[::1], types.float64[::1])
    )(
        _F2, _F3, _F2, _F1, _F1, types.float64, types.float64, types.intp, types.intp,
        types.float64, types.float64, types.float64, types.boolean, _I1, _F3, _F2,
    ),
    cache=True,
    error_model="numpy",
)  # fmt: skip
def levenberg_marquardt(
    q0, trot, tpos, lower, upper, tol_p, tol_r, max_iterations, stall_after, stall_ratio,
    damping, min_damping, clamp, q_index, placement, tool,
):  # fmt: skip
    """:func:`~gcm_pipeline.robot.ik.lm.levenberg_marquardt`, one (target, seed) pair at a time.

    The same iteration as the NumPy code, which runs it on all pairs at once:
    the pose error (position, log3 of the rotation error), converged when both
    are within the tolerances; from iteration ``stall_after`` on a pair whose
    score ``pe / tol_p + re / tol_r`` is not below ``stall_ratio`` times its
    score two iterations earlier stops (``stall_ratio`` 0: never); else the
    damped least-squares step with ``lam = damping |e|^2 + min_damping``, and
    with ``clamp`` the joints that would cross a limit frozen at it and the
    step re-solved with the others, then clipped to the limits.

    Args:
        q0: Seeds (M, nq) [rad].
        trot: Target rotations (M, 3, 3).
        tpos: Target positions (M, 3) [m].
        lower: Lower joint limits (nq,) [rad].
        upper: Upper joint limits (nq,) [rad].
        tol_p: Position tolerance [m].
        tol_r: Orientation tolerance [rad].
        max_iterations: Iterations (steps) per pair.
        stall_after: First iteration of the stall test.
        stall_ratio: Ratio of the stall test.
        damping: Damping factor of the squared error.
        min_damping: Smallest damping.
        clamp: Joint limits as above (else only the clip).
        q_index: Column of ``q`` of each joint of the chain (nj,).
        placement: Joint placements (nj, 4, 4).
        tool: The frame's placement on the last joint (4, 4).

    Returns:
        ``(q, converged, pos_err, rot_err)`` (M, nq), (M,) x 3; the errors of the returned q.
    """
    m, nq = q0.shape
    nj = q_index.shape[0]
    q_out = q0.copy()
    converged = np.zeros(m, dtype=np.bool_)
    pos_err = np.full(m, np.inf)
    rot_err = np.full(m, np.inf)
    frame = np.empty((nj, 3, 4))
    tcp = np.empty((3, 4))
    turn = np.empty((nj, 2))
    jac = np.empty((6, nj))
    e = np.empty(6)
    e_rest = np.empty(6)
    a = np.empty((6, 6))
    y = np.empty(6)
    dq = np.empty(nj)
    step = np.empty(nq)
    free = np.ones(nj, dtype=np.bool_)
    over = np.zeros(nj, dtype=np.bool_)
    score = np.empty(3)  # the last three iterations' scores (the stall test looks two back)
    for r in range(m):
        q = q_out[r]
        for i in range(3):
            score[i] = np.inf  # nothing of the previous pair
        for it in range(max_iterations + 1):
            for k in range(nj):
                turn[k, 0] = math.cos(q[q_index[k]])
                turn[k, 1] = math.sin(q[q_index[k]])
            _frames(turn, placement, tool, frame, tcp)
            _pose_error(trot[r], tpos[r], tcp, e)
            pe = math.sqrt(e[0] * e[0] + e[1] * e[1] + e[2] * e[2])
            re = math.sqrt(e[3] * e[3] + e[4] * e[4] + e[5] * e[5])
            pos_err[r] = pe
            rot_err[r] = re
            if pe <= tol_p and re <= tol_r:
                converged[r] = True
                break
            if stall_ratio > 0:
                score[it % 3] = pe / tol_p + re / tol_r
                if it >= stall_after and not score[it % 3] < stall_ratio * score[(it + 1) % 3]:
                    break
            if it == max_iterations:
                break
            _columns(frame, tcp, jac)
            squared = 0.0
            for i in range(6):
                squared += e[i] * e[i]
            lam = damping * squared + min_damping
            for k in range(nj):
                free[k] = True
            _damped_step(jac, e, lam, free, a, y, dq)
            for j in range(nq):
                step[j] = q[j]
            for k in range(nj):
                step[q_index[k]] += dq[k]
            if clamp:
                # any joint outside its limits (one outside the chain too, as the NumPy
                # code tests every column) re-solves the step from the clipped one
                crossed = False
                for j in range(nq):
                    crossed |= step[j] < lower[j] or step[j] > upper[j]
                for k in range(nj):
                    j = q_index[k]
                    over[k] = step[j] < lower[j] or step[j] > upper[j]
                if crossed:
                    # the joints that would cross a limit are frozen at it and the
                    # step is re-solved with the others (clamped DLS)
                    for i in range(6):
                        e_rest[i] = e[i]
                    for k in range(nj):
                        j = q_index[k]
                        at = min(max(step[j], lower[j]), upper[j])
                        for i in range(6):
                            e_rest[i] -= jac[i, k] * (at - q[j])
                        step[j] = at
                        free[k] = not over[k]
                    _damped_step(jac, e_rest, lam, free, a, y, dq)
                    for k in range(nj):
                        step[q_index[k]] += dq[k]
                for j in range(nq):
                    step[j] = min(max(step[j], lower[j]), upper[j])
            for j in range(nq):
                q[j] = step[j]
    return q_out, converged, pos_err, rot_err


@njit(
    types.Tuple((types.float64[::1], types.float64[::1]))(
        _F2, _F2, _I1, _F2, _F3, _F2, _I1, _F3, _F2
    ),
    cache=True,
    error_model="numpy",
)
def segment_samples(q_a, q_b, intervals, start, rot0, offsets, q_index, placement, tool):
    """The gripper's sampled deviation over joint segments (approach module's ``_segment_bounds``).

    Row m samples the joint segment ``q_a[m] -> q_b[m]`` at ``s = i / n``,
    ``i = 0 .. n`` with ``n = intervals[m]`` (0: the midpoint alone). Each
    sample's angles come from the previous one's by angle addition (one sine
    and cosine per joint and segment instead of per sample; they differ from
    ``cos(q_a + s (q_b - q_a))`` by a few ulps).

    Args:
        q_a: Segment starts (M, nq) [rad].
        q_b: Segment ends (M, nq) [rad].
        intervals: Intervals per segment (M,), >= 0.
        start: Start of each move's line (M, 3) [m].
        rot0: Grasp orientation of each move (M, 3, 3).
        offsets: Each move's displacement (M, 3) [m].
        q_index: Column of ``q`` of each joint of the chain (nj,).
        placement: Joint placements (nj, 4, 4).
        tool: The frame's placement on the last joint (4, 4).

    Returns:
        ``(dist, turn)`` (M,) each: the largest distance of a sample's frame
        origin from the move's line segment [m], and the largest
        ``||R - rot0||_F`` of a sample.
    """
    m = q_a.shape[0]
    nj = q_index.shape[0]
    dist = np.zeros(m)
    turned = np.zeros(m)
    frame = np.empty((nj, 3, 4))
    tcp = np.empty((3, 4))
    turn = np.empty((nj, 2))
    step = np.empty((nj, 2))
    for r in range(m):
        n = intervals[r]
        d0, d1, d2 = offsets[r, 0], offsets[r, 1], offsets[r, 2]
        length2 = max(d0 * d0 + d1 * d1 + d2 * d2, 1e-300)
        for k in range(nj):
            j = q_index[k]
            if n == 0:
                angle = 0.5 * (q_a[r, j] + q_b[r, j])
            else:
                angle = q_a[r, j]
                h = (q_b[r, j] - q_a[r, j]) / n
                step[k, 0] = math.cos(h)
                step[k, 1] = math.sin(h)
            turn[k, 0] = math.cos(angle)
            turn[k, 1] = math.sin(angle)
        for i in range(n + 1 if n else 1):
            if i:
                for k in range(nj):  # the next sample: each joint turned by its step
                    c, s = turn[k, 0], turn[k, 1]
                    turn[k, 0] = c * step[k, 0] - s * step[k, 1]
                    turn[k, 1] = s * step[k, 0] + c * step[k, 1]
            _frames(turn, placement, tool, frame, tcp)
            r0 = tcp[0, 3] - start[r, 0]
            r1 = tcp[1, 3] - start[r, 1]
            r2 = tcp[2, 3] - start[r, 2]
            t = min(max((r0 * d0 + r1 * d1 + r2 * d2) / length2, 0.0), 1.0)
            e0, e1, e2 = r0 - t * d0, r1 - t * d1, r2 - t * d2
            dist[r] = max(dist[r], math.sqrt(e0 * e0 + e1 * e1 + e2 * e2))
            squared = 0.0
            for a in range(3):
                for b in range(3):
                    squared += (tcp[a, b] - rot0[r, a, b]) ** 2
            turned[r] = max(turned[r], math.sqrt(squared))
    return dist, turned


@njit(cache=True, inline="always")
def _into_limits(angle: float, lower: float, upper: float) -> tuple[float, bool]:
    """An angle moved a turn up where below ``lower``, and whether it then lies in the limits."""
    if angle < lower:
        angle += 2.0 * math.pi
    return angle, lower <= angle <= upper


@njit(cache=True, inline="always")
def _wrap(angle: float) -> float:
    """An angle in (-2 pi, 2 pi) into [-pi, pi]."""
    if angle > math.pi:
        angle -= 2.0 * math.pi
    if angle < -math.pi:
        angle += 2.0 * math.pi
    return angle


@njit(
    types.Tuple((_I1W, types.float64[:, ::1], _I1W, _I1W))(
        _F3, _F2, _F2, _F1, _F1, _F2, types.float64, types.boolean, _F1
    ),
    cache=True,
    error_model="numpy",
)
def panda_ik(r7, p7, q7, lower, upper, ref, reach, near, dims):
    """:meth:`~gcm_pipeline.robot.ik.panda.PandaAnalyticIK.solve`, one (target, q7) at a time.

    The same closed form and pruning (see that module); the solutions come out
    in the same order: by target, column of ``q7``, branch.

    Args:
        r7: Rotations of DH frame 7 of the targets (N, 3, 3).
        p7: Positions of DH frame 7 (N, 3) [m].
        q7: Values of joint 7 (N, K) [rad].
        lower: Lower joint limits (7,) [rad].
        upper: Upper joint limits (7,) [rad].
        ref: With ``near``: reference configurations (N, 7) [rad].
        reach: With ``near``: largest change from the reference in every joint [rad].
        near: Only the solutions within ``reach`` of ``ref``.
        dims: ``(k, rho4, gamma, a4, a5, a7, d1, d3, d5)`` of the solver.

    Returns:
        ``(index, q, branch, column)`` (M,), (M, 7), (M,), (M,).
    """
    n, cols = q7.shape
    k_, rho4, gamma, a4, a5, a7, d1, d3, d5 = (
        dims[0], dims[1], dims[2], dims[3], dims[4], dims[5], dims[6], dims[7], dims[8]
    )  # fmt: skip
    cap = n * cols * 8
    out_t = np.empty(cap, dtype=np.intp)
    out_q = np.empty((cap, 7))
    out_b = np.empty(cap, dtype=np.intp)
    out_c = np.empty(cap, dtype=np.intp)
    x6, y6, z6, u = np.empty(3), np.empty(3), np.empty(3), np.empty(3)
    x4, y4, z4, z3, w = np.empty(3), np.empty(3), np.empty(3), np.empty(3), np.empty(3)
    q = np.empty(7)
    count = 0
    for i in range(n):
        for col in range(cols):
            q7v = q7[i, col]
            if not lower[6] <= q7v <= upper[6] or (near and not abs(q7v - ref[i, 6]) <= reach):
                continue
            c7, s7 = math.cos(q7v), math.sin(q7v)
            # frame 6: x6 = R7 (c7, -s7, 0), z6 = R7 (s7, c7, 0), y6 = -z7; O6 - O2
            for a in range(3):
                x6[a] = r7[i, a, 0] * c7 - r7[i, a, 1] * s7
                z6[a] = r7[i, a, 0] * s7 + r7[i, a, 1] * c7
                y6[a] = -r7[i, a, 2]
                u[a] = p7[i, a] - a7 * x6[a]
            u[2] = u[2] - d1
            length2 = u[0] * u[0] + u[1] * u[1] + u[2] * u[2]
            half = math.acos((length2 - k_) / rho4)  # NaN out of reach
            length = math.sqrt(length2)
            for a in range(3):
                u[a] = u[a] / length
            xu = x6[0] * u[0] + x6[1] * u[1] + x6[2] * u[2]
            yu = y6[0] * u[0] + y6[1] * u[1] + y6[2] * u[2]
            centre = math.atan2(xu, yu)
            for elbow in range(2):
                # 1. the elbow
                q4, ok = _into_limits(_wrap(gamma + half if elbow == 0 else gamma - half),
                                      lower[3], upper[3])  # fmt: skip
                if not ok or (near and not abs(q4 - ref[i, 3]) <= reach):
                    continue
                c4, s4 = math.cos(q4), math.sin(q4)
                ux = (a5 + a4 * c4 + d3 * s4) / length
                uy = (d5 - a4 * s4 + d3 * c4) / length
                spread = math.acos(uy / math.hypot(xu, yu))
                for wrist in range(2):
                    # 2. joint 6
                    q6, ok = _into_limits(
                        _wrap(centre + spread if wrist == 0 else centre - spread),
                        lower[5], upper[5],
                    )  # fmt: skip
                    if not ok or (near and not abs(q6 - ref[i, 5]) <= reach):
                        continue
                    s6, c6 = math.sin(q6), math.cos(q6)
                    for a in range(3):
                        y4[a] = s6 * x6[a] + c6 * y6[a]
                        w[a] = (y4[a] - uy * u[a]) / ux
                    z4[0] = u[1] * w[2] - u[2] * w[1]
                    z4[1] = u[2] * w[0] - u[0] * w[2]
                    z4[2] = u[0] * w[1] - u[1] * w[0]
                    for a in range(3):
                        x4[a] = ux * u[a] - uy * w[a]
                    for a in range(3):
                        z3[a] = s4 * x4[a] + c4 * y4[a]
                    x3z = c4 * x4[2] - s4 * y4[2]
                    sb = math.hypot(z3[0], z3[1])
                    q5 = math.atan2(
                        x4[0] * z6[0] + x4[1] * z6[1] + x4[2] * z6[2],
                        z4[0] * z6[0] + z4[1] * z6[1] + z4[2] * z6[2],
                    )
                    for shoulder in range(2):
                        # 3. the shoulder (two roots) and joint 5
                        sign = 1.0 if shoulder == 0 else -1.0
                        q[0] = math.atan2(sign * z3[1], sign * z3[0])
                        q[1] = math.atan2(sign * sb, z3[2])
                        q[2] = math.atan2(-sign * z4[2], -sign * x3z)
                        q[3], q[4], q[5], q[6] = q4, q5, q6, q7v
                        ok = True
                        for j in (0, 1, 2, 4):
                            q[j], inside = _into_limits(q[j], lower[j], upper[j])
                            ok &= inside
                        if ok and near:
                            for j in range(7):
                                ok &= abs(q[j] - ref[i, j]) <= reach
                        if not ok:
                            continue
                        out_t[count] = i
                        out_q[count] = q
                        out_b[count] = 4 * elbow + 2 * wrist + shoulder
                        out_c[count] = col
                        count += 1
    return out_t[:count].copy(), out_q[:count].copy(), out_b[:count].copy(), out_c[:count].copy()
