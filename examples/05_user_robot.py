"""A robot the project does not ship: a UR10 with a gripper, from a user's robot spec.

    python examples/05_user_robot.py [OUT_DIR]

configs/robots/ur10.yaml loads example-robot-data's UR10 (a bare flange) and
mounts a parallel-jaw gripper on it (the spec's `tool`: boxes and a cylinder,
the TCP frame `gripper_tcp`). Any YAML spec of this form works by path.
"""

import sys
import tempfile
from pathlib import Path

import gcm_pipeline as gcm

ROOT = Path(__file__).resolve().parent.parent
out = Path(sys.argv[1]) if len(sys.argv) > 1 else Path(tempfile.mkdtemp(prefix="gcm-"))
spec = ROOT / "configs/robots/ur10.yaml"

robot = gcm.load_robot(spec)
print(f"{robot.name}: {robot.nq} joints {robot.joint_names}")
print(f"grasp frame {robot.grasp_frame!r}, reach {robot.max_reach:.3f} m")
# The tool's collision shapes are part of the robot (named tool/<name>).
geometry = robot.build_geometry("collision")
print("tool shapes:", [g.name for g in geometry.geometryObjects if g.name.startswith("tool/")])

# The bottle example with this robot instead of the Panda (fewer grasps: fast).
overrides = [f"robot.spec={spec}", "candidates.count=36", "publish.html=false"]
pipeline = gcm.Pipeline.from_yaml(ROOT / "configs/bottle_side.yaml", overrides)
result = pipeline.run(out / "bottle_ur10", progress=False, force=True)

counts = result.counts
print(f"reachable with the UR10: {counts['reachable']} of {counts['densified']} grasps")
best = result.top(1)[0]
print("best grasp's joints [rad]:", [round(v, 3) for v in best["q"]])
print(f"run directory: {result.run_dir}")
