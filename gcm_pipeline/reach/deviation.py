r"""The bound of a joint path's deviation from its move's straight line.

Deviation bound. Along a segment :math:`q(s) = q_a + s\,\Delta q` the grasp
frame's position :math:`p(s)` has :math:`|p''| \le K = \sum_{j,k} r_{\max(j,k)}
|\Delta q_j| |\Delta q_k|`, with :math:`r_k` a bound of the distance of the
grasp frame from joint :math:`k`'s axis (the link lengths beyond it), because
:math:`\partial^2 p / \partial q_j \partial q_k = a_j \times (a_k \times (p -
o_k))` for :math:`j \le k`. Sampled at spacing :math:`h`, the distance of
:math:`p(s)` from the line segment is at most the largest sampled distance plus
:math:`K h^2 / 8` (the error of linear interpolation; the distance to a
segment is convex). Likewise :math:`\|R''\|_F \le \tfrac{3}{\sqrt 2} A^2` with
:math:`A = \sum_j |\Delta q_j|`, so :math:`\|R(s) - R_g\|_F` is at most its
largest sample plus :math:`\tfrac{3}{8\sqrt 2} A^2 h^2`. A point of the gripper
at distance at most :math:`\rho` from the grasp frame then leaves its straight
path by at most ``position bound`` + :math:`\rho` ``rotation bound``: that is
the deviation compared with ``max_deviation``. The samples are dense enough
for the :math:`h^2` terms to use at most a quarter of it.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import pinocchio as pin

from gcm_pipeline.robot import kernels
from gcm_pipeline.robot.collision import gripper_links
from gcm_pipeline.robot.model import Robot

__all__ = ["gripper_radius", "lever_arms", "sample_deviation", "segment_bounds"]

#: At most this many samples per segment (a segment needing more is split).
_MAX_SAMPLES = 64


def gripper_radius(robot: Robot) -> float:
    """Largest distance of a point of the gripper's collision geometry from the grasp frame [m].

    The gripper is the robot's hand (:func:`~gcm_pipeline.robot.collision.gripper_links`,
    rigid in the reduced model); each geometry is bounded by the corners of
    its local bounding box.
    """
    cached = robot.cache.get("gripper_radius")
    if cached is not None:
        return float(cached)
    links = gripper_links(robot)
    gm = robot.build_geometry("collision")
    model = robot.model
    data, gd = model.createData(), pin.GeometryData(gm)
    pin.forwardKinematics(model, data, robot.home)
    pin.updateGeometryPlacements(model, data, gm, gd)
    pin.updateFramePlacement(model, data, robot.grasp_frame_id)
    inv = data.oMf[robot.grasp_frame_id].inverse()
    radius = 0.0
    for k, go in enumerate(gm.geometryObjects):
        if model.frames[go.parentFrame].name not in links:
            continue
        go.geometry.computeLocalAABB()
        box = go.geometry.aabb_local
        lo, hi = np.asarray(box.min_, dtype=float), np.asarray(box.max_, dtype=float)
        corners = np.array(
            [[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])]
        )
        m = (inv * gd.oMg[k]).homogeneous
        pts = corners @ m[:3, :3].T + m[:3, 3]
        radius = max(radius, float(np.linalg.norm(pts, axis=1).max()))
    robot.cache["gripper_radius"] = radius
    return radius


def lever_arms(robot: Robot) -> np.ndarray:
    """Bounds (nq,) [m] of the grasp frame's distance from each joint's axis, by q index.

    The sum of the link offsets from the joint's origin to the grasp frame
    (see :meth:`~gcm_pipeline.robot.chain.KinematicChain.link_lengths`).
    """
    cached = robot.cache.get("lever_arms")
    if cached is not None:
        return np.array(cached)
    chain = robot.chain
    lengths = chain.link_lengths()  # joint k -> k+1 ..., last -> frame
    beyond = np.cumsum(lengths[::-1])[::-1]  # from joint k's origin to the frame
    out = np.zeros(robot.nq)
    out[chain.q_index] = beyond
    robot.cache["lever_arms"] = out.copy()
    return out


def segment_bounds(
    robot: Robot,
    lever: np.ndarray,
    q_a: np.ndarray,
    q_b: np.ndarray,
    start: np.ndarray,
    rot0: np.ndarray,
    offsets: np.ndarray,
    radius: float,
    budget: float,
    reject_above: float = np.inf,
) -> np.ndarray:
    """Bound of the gripper's deviation (M,) [m] over the joint segments ``q_a -> q_b``.

    Args:
        robot: The robot.
        lever: :func:`lever_arms` (nq,).
        q_a: Segment starts (M, nq) [rad].
        q_b: Segment ends (M, nq) [rad].
        start: Start of each move's line, the grasp position (M, 3) [m].
        rot0: Grasp orientation (M, 3, 3).
        offsets: Each move's displacement (M, 3) [m].
        radius: Largest distance of a gripper point from the grasp frame [m].
        budget: What the h^2 terms may use [m]; more samples if needed.
        reject_above: Segments whose deviation at the midpoint already exceeds
            this [m] get that value (a lower bound of their bound) without
            further samples.
    """
    m = q_a.shape[0]
    if m == 0:
        return np.zeros(0)
    out = np.empty(m)
    todo = np.arange(m)
    compiled = kernels.get()
    if np.isfinite(reject_above):
        if compiled is not None:
            dist, turn = _samples(
                compiled, robot, q_a, q_b, np.zeros(m, dtype=np.intp), start, rot0, offsets
            )
            mid = dist + radius * turn
        else:
            mid = sample_deviation(robot, 0.5 * (q_a + q_b), start, rot0, offsets, radius)
        far = mid > reject_above
        out[far] = mid[far]
        todo = np.flatnonzero(~far)
        if todo.size == 0:
            return out
        # np.take: a row gather several times faster than NumPy's fancy indexing
        q_a, q_b, start, rot0, offsets = (
            a.take(todo, axis=0) for a in (q_a, q_b, start, rot0, offsets)
        )
        m = todo.size
    dq = np.abs(q_b - q_a)
    k_pos, a_rot = _curvature_sums(dq, lever, robot.chain.q_index)  # |p''| bound [m]
    k_rot = 3.0 / np.sqrt(2.0) * a_rot**2  # ||R''||_F bound
    curvature = k_pos + radius * k_rot
    # h^2 / 8 * curvature <= budget  ->  intervals n >= sqrt(curvature / (8 budget)),
    # rounded up to a power of two so that rows share a few sample counts
    need = np.sqrt(curvature / (8.0 * budget))
    n_rows = np.clip(2 ** np.ceil(np.log2(np.maximum(need, 2.0))), 2, _MAX_SAMPLES).astype(np.intp)
    if compiled is not None:
        dist, turn = _samples(compiled, robot, q_a, q_b, n_rows, start, rot0, offsets)
        h2 = 1.0 / n_rows**2
        out[todo] = dist + k_pos * h2 / 8.0 + radius * (turn + k_rot * h2 / 8.0)
        return out
    res = np.empty(m)
    for n in np.unique(n_rows).tolist():
        sel = np.flatnonzero(n_rows == n)
        s = np.linspace(0.0, 1.0, n + 1)
        qa, qb = q_a[sel], q_b[sel]
        qs = qa[:, None, :] + s[None, :, None] * (qb - qa)[:, None, :]
        rot, pos = robot.chain.pose(qs.reshape(-1, robot.nq))
        pos = pos.reshape(sel.size, n + 1, 3)
        rot = rot.reshape(sel.size, n + 1, 9)
        # distance of each sample from its move's line segment
        d = offsets[sel]
        rel = pos - start[sel, None, :]
        t = (
            np.einsum("msj,mj->ms", rel, d)
            / np.maximum(np.einsum("ij,ij->i", d, d), 1e-300)[:, None]
        )
        t = np.clip(t, 0.0, 1.0)
        dist = np.linalg.norm(rel - t[:, :, None] * d[:, None, :], axis=2).max(axis=1)
        rdist = np.linalg.norm(rot - rot0[sel].reshape(-1, 1, 9), axis=2).max(axis=1)
        h2 = 1.0 / n**2
        res[sel] = dist + k_pos[sel] * h2 / 8.0 + radius * (rdist + k_rot[sel] * h2 / 8.0)
    out[todo] = res
    return out


def _curvature_sums(
    dq: np.ndarray, lever: np.ndarray, order: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """The sums of the curvature bounds of segments with joint changes ``|dq|`` (M, nq).

    ``k_pos = sum_k lever_k d_k (d_k + 2 before_k)`` over the chain's joints
    ``order`` (``before_k``: the sum of ``d`` over the joints before k) and
    ``a_rot = sum_j dq_j``, each summed joint by joint, left to right, without
    NumPy's slow reductions along a short last axis. ``cumsum`` adds in this
    order, and ``sum`` over a row of up to 7 values too (equal to the bit);
    over 8 or more NumPy adds in pairwise blocks, so an arm with 8 or more
    joints may differ from ``sum`` in the last bit (a bound either way).
    """
    lev = lever[order]
    k_pos = np.zeros(dq.shape[0])
    total = np.zeros(dq.shape[0])  # sum of d up to joint k
    for k, j in enumerate(order.tolist()):
        d = dq[:, j]
        total = d.copy() if k == 0 else total + d
        term = lev[k] * d * (d + 2.0 * (total - d))
        k_pos = term if k == 0 else k_pos + term
    a_rot = dq[:, 0].copy()
    for j in range(1, dq.shape[1]):
        a_rot += dq[:, j]
    return k_pos, a_rot


def _samples(compiled: Any, robot: Robot, *arrays: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The compiled kernel's deviation samples (its arguments as C arrays)."""
    out: tuple[np.ndarray, np.ndarray] = compiled.segment_samples(
        *(np.ascontiguousarray(a) for a in arrays), *robot.chain.packed
    )
    return out


def sample_deviation(
    robot: Robot,
    q: np.ndarray,
    start: np.ndarray,
    rot0: np.ndarray,
    offsets: np.ndarray,
    radius: float,
) -> np.ndarray:
    """Sampled deviation (M,) [m] at configurations ``q`` (M, nq) [rad].

    The distance of the grasp frame from its move's line segment plus
    ``radius`` times the orientation change ``||R - R_g||_F``.
    """
    rot, pos = robot.chain.pose(q)
    rel = pos - start
    t = np.einsum("ij,ij->i", rel, offsets) / np.maximum(
        np.einsum("ij,ij->i", offsets, offsets), 1e-300
    )
    t = np.clip(t, 0.0, 1.0)
    dist = np.linalg.norm(rel - t[:, None] * offsets, axis=1)
    rdist = np.linalg.norm((rot - rot0).reshape(-1, 9), axis=1)
    return dist + radius * rdist
