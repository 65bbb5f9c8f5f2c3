"""Compiled kernels of a kinematic chain: forward kinematics, and samples along segments.

* :func:`chain_forward`: the kernel of :meth:`KinematicChain._forward
  <gcm_pipeline.robot.chain.KinematicChain>` (its NumPy reference, beside this module);
* :func:`joint_frames`: the kernel of :meth:`JointFrames.compute
  <gcm_pipeline.robot.chain.JointFrames>` (every joint's frame, for the collision checks),
  with :func:`cos_sin`, the cosines and sines of its angles;
* :func:`segment_samples`: the deviation samples of
  :func:`gcm_pipeline.reach.deviation.segment_bounds` (its NumPy reference lives in
  the reach package, a layer above the robot's: the kernel stays here, with the
  chain's frames it samples);
* :func:`grid_path`: a move's joint path at its grid points, piecewise linear
  through its waypoints (the NumPy reference is ``_grid_path`` of
  :mod:`gcm_pipeline.reach.path`, a layer above).

Imported by :func:`gcm_pipeline.robot.kernels.get` only (it imports Numba); the
inline pieces come from :mod:`~gcm_pipeline.robot.kernel_common`.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit, types

from gcm_pipeline.robot.kernel_common import F2, F3, I1, I2, dot4, fma, frames, jacobian_columns


@njit(
    types.Tuple((types.float64[:, :, ::1], types.float64[:, ::1], types.float64[:, :, ::1]))(
        F2, I1, F3, F2, types.intp, types.boolean
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
        frames(turn, placement, tool, frame, tcp)
        for r in range(3):
            for col in range(3):
                rot[i, r, col] = tcp[r, col]
            pos[i, r] = tcp[r, 3]
        if not jacobian:
            continue
        jacobian_columns(frame, tcp, columns)
        for k in range(nj):
            for a in range(6):
                jac[i, a, q_index[k]] = columns[a, k]
    return rot, pos, jac


@njit(
    types.Tuple((types.float64[::1], types.float64[::1]))(F2, F2, I1, F2, F3, F2, I1, F3, F2),
    cache=True,
    error_model="numpy",
)
def segment_samples(q_a, q_b, intervals, start, rot0, offsets, q_index, placement, tool):
    """The gripper's sampled deviation over joint segments (as ``segment_bounds`` samples it).

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
            frames(turn, placement, tool, frame, tcp)
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


@njit(
    types.Tuple((types.float64[:, :, ::1], types.intp[::1]))(I2, F2, types.intp, types.float64),
    cache=True,
)
def grid_path(slot, knots, sub, max_step):
    """Joint paths at the grid points, piecewise linear through the waypoints, and their jumps.

    Row m's waypoints sit at the fine positions ``p`` with ``slot[m, p] >= 0``
    (configuration ``knots[slot[m, p]]``), among them the first and the last.
    Grid point ``g`` (fine position ``g * sub``) lies between the last waypoint
    at or before it (``a``) and the first at or after it (``b``):
    ``(q_b - q_a) * f + q_a`` with ``f = (g sub - a) / max(b - a, 1)``, the
    NumPy code's operations in its order (equal to the bit). The jump of grid
    step ``g`` is the largest ``|q_g+1 - q_g|`` over the joints, NaN if one is
    (as ``np.maximum`` propagates it).

    Args:
        slot: Row of ``knots`` at each fine position of each path (M, steps * sub + 1), -1: none.
        knots: The waypoints (K, nq) [rad].
        sub: Fine positions per grid step, >= 1.
        max_step: Largest jump allowed per grid step [rad].

    Returns:
        ``(path, over)``: the grid points (M, steps + 1, nq) and each path's
        first grid step (0-based) whose jump exceeds ``max_step``, -1 if none.
    """
    m, width = slot.shape
    steps = (width - 1) // sub
    nq = knots.shape[1]
    path = np.empty((m, steps + 1, nq))
    over = np.full(m, -1, dtype=np.intp)
    for r in range(m):
        for g in range(steps + 1):
            at = g * sub
            a = at
            while a > 0 and slot[r, a] < 0:
                a -= 1
            b = at
            while b < width - 1 and slot[r, b] < 0:
                b += 1
            f = (at - a) / max(b - a, 1)
            ka = slot[r, a]
            kb = slot[r, b]
            for j in range(nq):
                path[r, g, j] = (knots[kb, j] - knots[ka, j]) * f + knots[ka, j]
            if g == 0 or over[r] >= 0:
                continue
            nan, big = False, False
            for j in range(nq):
                d = abs(path[r, g, j] - path[r, g - 1, j])
                if d != d:
                    nan = True
                elif d > max_step:
                    big = True
            if big and not nan:
                over[r] = g - 1
    return path, over


#: ``1.5 * 2**52``: ``(t + MAGIC) - MAGIC`` rounds ``|t| < 2**51`` to an integer
#: (round half to even), in a loop LLVM vectorises (no libm call, no conversion).
MAGIC = 6755399441055744.0
#: ``2 / pi`` and ``pi / 2`` in three parts (fdlibm's ``e_rem_pio2.c``: 33 + 33 + 53 bits),
#: so that ``k * PIO2_1`` and ``k * PIO2_2`` are exact for ``|k| < 2**20``.
INVPIO2 = 6.36619772367581382433e-01
PIO2_1 = 1.57079632673412561417e00
PIO2_2 = 6.07710050630396597660e-11
PIO2_2T = 2.02226624879595063154e-21
#: fdlibm's minimax polynomials of ``sin`` and ``cos`` on ``[-pi/4, pi/4]`` (``k_sin.c``,
#: ``k_cos.c``: errors below 2**-58).
S1, S2, S3 = -1.66666666666666324348e-01, 8.33333333332248946124e-03, -1.98412698298579493134e-04
S4, S5, S6 = 2.75573137070700676789e-06, -2.50507602534068634195e-08, 1.58969099521155010221e-10
C1, C2, C3 = 4.16666666666666019037e-02, -1.38888888888741095749e-03, 2.48015872894767294178e-05
C4, C5, C6 = -2.75573143513906633035e-07, 2.08757232129817482790e-09, -1.13596475577881948265e-11
#: Largest ``|q|`` [rad] :func:`cos_sin` reduces itself; libm's ``cos`` and ``sin`` the others.
REDUCED = 1e5


@njit(types.Tuple((types.float64[:, ::1], types.float64[:, ::1]))(F2), cache=True)
def cos_sin(q):
    """``(np.cos(q), np.sin(q))`` to about an ulp, in one loop LLVM vectorises.

    NumPy's float64 ``cos`` and ``sin`` call libm once per element (about
    11 ns each here); this computes both from one range reduction,
    ``q = k pi/2 + r`` with ``|r| <= pi/4`` (``pi/2`` in three parts: ``r`` to
    about an ulp of itself), fdlibm's polynomials for ``sin r`` and ``cos r``,
    and the quadrant ``k mod 4`` chosen by selects (about 1.5 ns per angle with
    AVX-512). Angles beyond :data:`REDUCED` (and inf, nan) get libm's values.
    The results differ from libm's by at most an ulp or two (tested); the
    frames that use them are compared with Pinocchio's to 1e-12.

    Args:
        q: Angles (N, M) [rad].

    Returns:
        Their cosines and sines, (N, M) each.
    """
    n, m = q.shape
    cos = np.empty((n, m))
    sin = np.empty((n, m))
    angle = q.reshape(n * m)
    c_out = cos.reshape(n * m)
    s_out = sin.reshape(n * m)
    for i in range(n * m):
        x = angle[i]
        k = (x * INVPIO2 + MAGIC) - MAGIC
        r = ((x - k * PIO2_1) - k * PIO2_2) - k * PIO2_2T
        z = r * r
        s = r + r * z * (S1 + z * (S2 + z * (S3 + z * (S4 + z * (S5 + z * S6)))))
        s = math.copysign(s, r)  # sin r has r's sign; -0.0 + 0.0 alone would give +0.0
        hz = 0.5 * z
        w = 1.0 - hz
        poly = z * z * (C1 + z * (C2 + z * (C3 + z * (C4 + z * (C5 + z * C6)))))
        c = w + (((1.0 - w) - hz) + poly)
        # k mod 4 as k/4 minus its nearest integer: 0, 0.25, +-0.5 (ties to even), -0.25
        t = k * 0.25
        t = t - ((t + MAGIC) - MAGIC)
        odd = abs(t) == 0.25  # quadrants 1 and 3: sine and cosine swap
        sign_s = -1.0 if (t < 0.0 or t == 0.5) else 1.0  # quadrants 2 and 3
        sign_c = -1.0 if (t > 0.0 or t == -0.5) else 1.0  # quadrants 1 and 2
        s_out[i] = sign_s * (c if odd else s)
        c_out[i] = sign_c * (s if odd else c)
    for i in range(n * m):
        x = angle[i]
        if not abs(x) <= REDUCED:  # far, inf or nan
            c_out[i] = math.cos(x)
            s_out[i] = math.sin(x)
    return cos, sin


@njit(types.float64[:, :, :, ::1](F2, F2, I1, I1, F3), cache=True)
def joint_frames(cos_q, sin_q, parent, q_index, placement):
    """:meth:`~gcm_pipeline.robot.chain.JointFrames.compute`, one configuration at a time.

    ``frame[j] = frame[parent[j]] @ placement[j]``, then turned about z by its
    angle as in :func:`~gcm_pipeline.robot.kernel_common.frames` (the summation
    order of NumPy's: OpenBLAS's FMA chain, the complex product's FMAs; the
    angle's cosine and sine from :func:`cos_sin`, within an ulp or two of the
    NumPy code's, so the frames equal its frames to round-off, not to the bit);
    joint 0 is the identity and a child of joint 0 starts from its placement.

    Args:
        cos_q: Cosines of the configurations' angles (N, nq) (:func:`cos_sin`: the
            kernel's scalar libm calls would cost more than all its products).
        sin_q: Their sines (N, nq).
        parent: Parent of each joint (J,).
        q_index: Column of ``q`` of each joint, unused for joint 0 (J,).
        placement: Joint placements (J, 4, 4), axes turned onto z.

    Returns:
        Every joint's frame (J, N, 3, 4).
    """
    n = cos_q.shape[0]
    nj = parent.shape[0]
    out = np.empty((nj, n, 3, 4))
    for i in range(n):
        for r in range(3):
            for col in range(4):
                out[0, i, r, col] = 1.0 if r == col else 0.0
        for j in range(1, nj):
            p = parent[j]
            f = out[j, i]
            for r in range(3):
                if p == 0:
                    for col in range(4):
                        f[r, col] = placement[j, r, col]
                else:
                    for col in range(4):
                        f[r, col] = dot4(out[p, i], r, placement[j], col)
            c = cos_q[i, q_index[j]]
            s = -sin_q[i, q_index[j]]
            for r in range(3):
                x = f[r, 0]
                y = f[r, 1]
                f[r, 0] = fma(x, c, -(y * s))
                f[r, 1] = fma(x, s, y * c)
    return out
