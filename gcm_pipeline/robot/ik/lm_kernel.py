"""Compiled kernel of the IK's Levenberg-Marquardt iterations, one (target, seed) pair at a time.

The kernel of :func:`gcm_pipeline.robot.ik.lm.levenberg_marquardt` (the NumPy
reference, beside this module). Imported by :func:`gcm_pipeline.robot.kernels.get`
only (it imports Numba); the chain's frames come from
:mod:`~gcm_pipeline.robot.kernel_common`.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
from numba import njit, types

from gcm_pipeline.robot.kernel_common import F1, F2, F3, I1, frames, jacobian_columns


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


@njit(cache=True, inline="always")
def _clamp(
    q: Any, step: Any, e: Any, jac: Any, lam: float, lower: Any, upper: Any, q_index: Any,
    free: Any, over: Any, e_rest: Any, a: Any, y: Any, dq: Any,
) -> None:  # fmt: skip
    """The step ``step`` (nq,) from ``q`` kept in the limits, in place (clamped DLS).

    Any joint outside its limits (one outside the chain too, as the NumPy code
    tests every column) re-solves the step from the clipped one: the joints that
    would cross a limit are frozen at it and the step is re-solved with the
    others; then the step is clipped to the limits. ``free``, ``over``,
    ``e_rest``, ``a``, ``y`` and ``dq`` are scratch arrays.
    """
    nq = step.shape[0]
    nj = q_index.shape[0]
    crossed = False
    for j in range(nq):
        crossed |= step[j] < lower[j] or step[j] > upper[j]
    for k in range(nj):
        j = q_index[k]
        over[k] = step[j] < lower[j] or step[j] > upper[j]
    if crossed:
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


@njit(
    types.Tuple(
        (types.float64[:, ::1], types.boolean[::1], types.float64[::1], types.float64[::1])
    )(
        F2, F3, F2, F1, F1, types.float64, types.float64, types.intp, types.intp,
        types.float64, types.float64, types.float64, types.boolean, I1, F3, F2,
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
            frames(turn, placement, tool, frame, tcp)
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
            jacobian_columns(frame, tcp, jac)
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
                _clamp(q, step, e, jac, lam, lower, upper, q_index, free, over, e_rest, a, y, dq)
            for j in range(nq):
                q[j] = step[j]
    return q_out, converged, pos_err, rot_err
