"""Test poses shared by the IK tests."""

from __future__ import annotations

import numpy as np

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
