"""Test poses and pose comparisons shared by the tests."""

from __future__ import annotations

import numpy as np
import pinocchio as pin

from gcm_pipeline.geometry.dualquat import dq_to_matrix
from gcm_pipeline.robot.model import Robot


def backward_poses(
    robot: Robot, n: int, rng: np.random.Generator, lo: float, hi: float | None = None
) -> np.ndarray:
    """Poses (n, 4, 4) at ``lo``-``hi`` [m] from the shoulder (``lo`` if ``hi`` is None),
    approach axis (z) pointing back at it.

    Beyond ``max_reach`` they are pre-filtered. Inside it, from about 0.6 m (the
    Panda), the hand would have to reach back past its own wrist: no configuration
    exists, and the Panda's reach proof says so before any IK (``out_of_reach``).
    """
    d = rng.normal(size=(n, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    x = np.cross(-d, rng.normal(size=(n, 3)))
    x /= np.linalg.norm(x, axis=1, keepdims=True)
    out = np.tile(np.eye(4), (n, 1, 1))
    out[:, :3, 0], out[:, :3, 1], out[:, :3, 2] = x, np.cross(-d, x), -d
    dist = lo if hi is None else rng.uniform(lo, hi, size=(n, 1))
    out[:, :3, 3] = robot.shoulder + dist * d
    return out


def same_pose(a: np.ndarray, b: np.ndarray, atol: float = 1e-10) -> bool:
    """Dual quaternions (..., 8) of the same poses: equal up to the double cover (q ~ -q)."""
    return np.allclose(dq_to_matrix(a), dq_to_matrix(b), atol=atol)


def equal_up_to_sign(a: np.ndarray, b: np.ndarray, atol: float = 1e-10) -> bool:
    """Quaternions (..., 4) or dual quaternions (..., 8) equal up to the sign of each one.

    The sign is the one of the real parts' dot product, so ``a`` and ``-b`` compare
    equal, and ``a`` and ``b`` differing in anything but the sign do not.
    """
    s = np.sign(np.einsum("...i,...i->...", a[..., :4], b[..., :4]))[..., None]
    return np.allclose(a, s * b, atol=atol)


def pin_poses(robot: Robot, q: np.ndarray) -> np.ndarray:
    """Grasp-frame poses (N, 4, 4) of configurations ``q`` (N, nq) by Pinocchio itself."""
    data = robot.model.createData()
    out = np.empty((len(q), 4, 4))
    for i, qi in enumerate(q):
        pin.forwardKinematics(robot.model, data, qi)
        pin.updateFramePlacements(robot.model, data)
        out[i] = data.oMf[robot.grasp_frame_id].homogeneous
    return out
