"""Ask a run's grasp manifold for the reachable grasp nearest to a pose.

    python examples/02_query.py [OUT_DIR]

Every point of a manifold triangle is a grasp, not only the rows of the run.
The answer comes with a joint solution checked like the run's rows (IK,
collisions, approach).
"""

import sys
import tempfile
from pathlib import Path

import numpy as np

import gcm_pipeline as gcm

ROOT = Path(__file__).resolve().parent.parent
out = Path(sys.argv[1]) if len(sys.argv) > 1 else Path(tempfile.mkdtemp(prefix="gcm-"))

# A run to query (a run directory written before works the same way).
pipeline = gcm.Pipeline.from_yaml(ROOT / "configs/bottle_side.yaml", ["publish.html=false"])
pipeline.run(out / "bottle", progress=False, force=True)
manifold = gcm.load_manifold(out / "bottle")

# The pose we would like to grasp at: position [m] and quaternion (w, x, y, z)
# of the gripper's grasp frame, in the world frame.
pose = gcm.dq_from_pos_quat([0.5, 0.0, 0.15], [0.5, 0.5, -0.5, 0.5])

where = manifold.locate(pose)  # the nearest point of the manifold, reachable or not
print(f"nearest manifold point: triangle {where.triangle[0]}, {where.distance[0]:.4f} m away")

near = manifold.nearest_reachable(pose)  # the nearest grasp the robot reaches
print(f"nearest reachable grasp: {near.distance[0]:.4f} m away (position + 0.1 m/rad)")
print("its joint solution [rad]:", np.round(near.q[0], 3).tolist())
