"""Compiled kernel of the Panda's closed-form IK, one (target, joint-7 value) at a time.

The kernel of :meth:`gcm_pipeline.robot.ik.panda.PandaAnalyticIK.solve` (the NumPy
reference, beside this module). Imported by :func:`gcm_pipeline.robot.kernels.get`
only (it imports Numba).
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
from numba import njit, types

from gcm_pipeline.robot.kernel_common import F1, F2, F3, I1W


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


@njit(cache=True, inline="always")
def _frame4(
    q6: float, s4: float, c4: float, ux: float, uy: float, x6: Any, y6: Any, u: Any,
    x4: Any, y4: Any, z4: Any, z3: Any, w: Any,
) -> float:  # fmt: skip
    """Frame 4's axes ``x4``, ``y4``, ``z4`` and ``z3`` (3,) from joint 6 and the elbow, in place.

    ``w`` is scratch; returns the z component of frame 3's x axis.
    """
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
    return c4 * x4[2] - s4 * y4[2]


@njit(cache=True, inline="always")
def _frame6(
    r7: Any, p7: Any, i: int, q7v: float, a7: float, d1: float, x6: Any, y6: Any, z6: Any, u: Any
) -> None:
    """Frame 6's axes of target ``i`` at joint 7 ``q7v`` and ``u`` = O6 - O2, in place."""
    c7, s7 = math.cos(q7v), math.sin(q7v)
    # x6 = R7 (c7, -s7, 0), z6 = R7 (s7, c7, 0), y6 = -z7
    for a in range(3):
        x6[a] = r7[i, a, 0] * c7 - r7[i, a, 1] * s7
        z6[a] = r7[i, a, 0] * s7 + r7[i, a, 1] * c7
        y6[a] = -r7[i, a, 2]
        u[a] = p7[i, a] - a7 * x6[a]
    u[2] = u[2] - d1


@njit(cache=True, inline="always")
def _kept(q: Any, i: int, lower: Any, upper: Any, ref: Any, reach: float, near: bool) -> bool:
    """Whether ``q`` is inside the limits (with ``near``: within ``reach`` of ``ref[i]``).

    Joints 1, 2, 3 and 5 are moved a turn up where below their limits, in place.
    """
    ok = True
    for j in (0, 1, 2, 4):
        q[j], inside = _into_limits(q[j], lower[j], upper[j])
        ok &= inside
    if ok and near:
        for j in range(7):
            ok &= abs(q[j] - ref[i, j]) <= reach
    return ok


@njit(cache=True, inline="always")
def _emit(
    out_t: Any, out_q: Any, out_b: Any, out_c: Any, count: int, i: int, q: Any, b: int, c: int
) -> int:
    """Write solution ``q`` (target ``i``, branch ``b``, column ``c``) at row ``count``."""
    out_t[count], out_b[count], out_c[count] = i, b, c
    out_q[count] = q
    return count + 1


@njit(cache=True, inline="always")
def _lever_distance(q: Any, pref: Any, i: int, levers: Any) -> float:
    """``sum(((q - pref[i]) * levers) ** 2)``, summed in joint order as NumPy sums a row."""
    d = 0.0
    for j in range(7):
        e = (q[j] - pref[i, j]) * levers[j]
        d += e * e
    return d


@njit(
    types.Tuple((I1W, types.float64[:, ::1], I1W, I1W))(
        F3, F2, F2, F1, F1, F2, types.float64, types.boolean, F1, F2, F1
    ),
    cache=True,
    error_model="numpy",
)
def panda_ik(r7, p7, q7, lower, upper, ref, reach, near, dims, pref, levers):
    """:meth:`~gcm_pipeline.robot.ik.panda.PandaAnalyticIK.solve`, one (target, q7) at a time.

    The same closed form and pruning (see that module); the solutions come out
    in the same order: by target, column of ``q7``, branch. With ``pref`` of
    (N, 7) rows (else (0, 7)): only each target's solution nearest ``pref[i]``
    in the ``levers``-weighted distance (the first of ties), as
    :meth:`~gcm_pipeline.robot.ik.panda.PandaAnalyticIK.nearest`.

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
        pref: Preferred configurations (N, 7) [rad], or (0, 7): every solution.
        levers: Weight of each joint in the distance to ``pref`` (7,) [m/rad].

    Returns:
        ``(index, q, branch, column)`` (M,), (M, 7), (M,), (M,).
    """
    n, cols = q7.shape
    k_, rho4, gamma, a4, a5, a7, d1, d3, d5 = (
        dims[0], dims[1], dims[2], dims[3], dims[4], dims[5], dims[6], dims[7], dims[8]
    )  # fmt: skip
    cap = n if pref.shape[0] > 0 else n * cols * 8
    out_t = np.empty(cap, dtype=np.intp)
    out_q = np.empty((cap, 7))
    out_b = np.empty(cap, dtype=np.intp)
    out_c = np.empty(cap, dtype=np.intp)
    x6, y6, z6, u = np.empty(3), np.empty(3), np.empty(3), np.empty(3)
    x4, y4, z4, z3, w = np.empty(3), np.empty(3), np.empty(3), np.empty(3), np.empty(3)
    q, best_q = np.empty(7), np.empty(7)
    nearest = pref.shape[0] > 0
    count = 0
    for i in range(n):
        best, best_b, best_c = np.inf, 0, -1  # best_c -1: none yet
        for col in range(cols):
            q7v = q7[i, col]
            if not lower[6] <= q7v <= upper[6] or (near and not abs(q7v - ref[i, 6]) <= reach):
                continue
            _frame6(r7, p7, i, q7v, a7, d1, x6, y6, z6, u)
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
                    x3z = _frame4(q6, s4, c4, ux, uy, x6, y6, u, x4, y4, z4, z3, w)
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
                        if not _kept(q, i, lower, upper, ref, reach, near):
                            continue
                        b = 4 * elbow + 2 * wrist + shoulder
                        if nearest:
                            d = _lever_distance(q, pref, i, levers)
                            # NumPy's stable sort: the first smallest, NaN after any number
                            if best_c < 0 or d < best or (best != best and d == d):
                                best, best_b, best_c = d, b, col
                                best_q[:] = q
                            continue
                        count = _emit(out_t, out_q, out_b, out_c, count, i, q, b, col)
        if best_c >= 0:
            count = _emit(out_t, out_q, out_b, out_c, count, i, best_q, best_b, best_c)
    return out_t[:count].copy(), out_q[:count].copy(), out_b[:count].copy(), out_c[:count].copy()
