"""Regenerate ``mug_grasps.npy``: 24 grasps on a mug, in ACRONYM's gripper convention.

The poses are in the mug's frame (a cylinder r = 0.04 m, h = 0.10 m standing on
its base) and use the gripper frame of ACRONYM's Franka gripper: origin at the
hand base, z = approach, fingers closing along x. ``configs/from_file.yaml``
maps them onto ``panda_hand_tcp`` with ``grasp_to_tool: {xyz: [0, 0, 0.1034],
rpy_deg: [0, 0, -90]}``.

Run from the repository root: ``PYTHONPATH=. python configs/data/make_mug_grasps.py``.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from gcm_pipeline.config import Pose
from gcm_pipeline.sources.generators import poses_cylinder_side

RADIUS, HEIGHT = 0.04, 0.10


def rim_grasps(count: int) -> np.ndarray:
    """Grasps from above across the mug's wall, 1 cm below the rim (tool frame)."""
    theta = 2 * np.pi * (np.arange(count) + 0.5) / count
    radial = np.stack([np.cos(theta), np.sin(theta), np.zeros(count)], axis=1)
    z = np.tile([0.0, 0.0, -1.0], (count, 1))
    x = np.cross(radial, z)
    t = np.zeros((count, 4, 4))
    t[:, :3, 0], t[:, :3, 1], t[:, :3, 2] = x, radial, z
    t[:, :3, 3] = radial * RADIUS
    t[:, 2, 3] = HEIGHT - 0.01
    t[:, 3, 3] = 1.0
    return t


def main() -> None:
    """Write mug_grasps.npy next to this script."""
    side = poses_cylinder_side(16, RADIUS, HEIGHT, rings=2, depth=0.01)
    # rings at 5 and 8 cm: lower, the hand would touch the table
    side[:, 2, 3] = np.where(side[:, 2, 3] < 0.5 * HEIGHT, 0.05, 0.08)
    tool = np.concatenate([side, rim_grasps(8)])
    grasp_to_tool = Pose(xyz=(0, 0, 0.1034), rpy_deg=(0, 0, -90)).matrix()
    gripper = tool @ np.linalg.inv(grasp_to_tool)
    np.save(Path(__file__).with_name("mug_grasps.npy"), gripper.round(12))


if __name__ == "__main__":
    main()
