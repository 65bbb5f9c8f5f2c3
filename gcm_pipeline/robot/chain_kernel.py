"""Compiled kernels of a kinematic chain: forward kinematics, and samples along segments.

* :func:`chain_forward`: the kernel of :meth:`KinematicChain._forward
  <gcm_pipeline.robot.chain.KinematicChain>` (its NumPy reference, beside this module);
* :func:`joint_frames`: the kernel of :meth:`JointFrames.compute
  <gcm_pipeline.robot.chain.JointFrames>` (every joint's frame, for the collision checks);
* :func:`segment_samples`: the deviation samples of
  :func:`gcm_pipeline.reach.deviation.segment_bounds` (its NumPy reference lives in
  the reach package, a layer above the robot's: the kernel stays here, with the
  chain's frames it samples).

Imported by :func:`gcm_pipeline.robot.kernels.get` only (it imports Numba); the
inline pieces come from :mod:`~gcm_pipeline.robot.kernel_common`.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit, types

from gcm_pipeline.robot.kernel_common import F2, F3, I1, dot4, fma, frames, jacobian_columns


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


@njit(types.float64[:, :, :, ::1](F2, F2, I1, I1, F3), cache=True)
def joint_frames(cos_q, sin_q, parent, q_index, placement):
    """:meth:`~gcm_pipeline.robot.chain.JointFrames.compute`, one configuration at a time.

    ``frame[j] = frame[parent[j]] @ placement[j]``, then turned about z by its
    angle as in :func:`~gcm_pipeline.robot.kernel_common.frames` (the summation
    order of NumPy's: OpenBLAS's FMA chain, the complex product's FMAs; the
    angle's cosine and sine from NumPy's ``cos`` and ``sin``, so the frames equal
    the NumPy code's to round-off, not to the bit);
    joint 0 is the identity and a child of joint 0 starts from its placement.

    Args:
        cos_q: Cosines of the configurations' angles (N, nq) (NumPy's vectorised
            cosine: the kernel's scalar one costs more than all its products).
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
