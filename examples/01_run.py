"""Run the bottle example from Python and print its best grasps.

    python examples/01_run.py [OUT_DIR]

The config is the paper's bottle (configs/bottle_side.yaml): side grasps on
rings around a cylinder, a Panda, a table. The run directory (grasps.csv,
summary.json, plots, ...) is written into OUT_DIR (default: a temp folder).
"""

import sys
import tempfile
from pathlib import Path

import gcm_pipeline as gcm

ROOT = Path(__file__).resolve().parent.parent
out = Path(sys.argv[1]) if len(sys.argv) > 1 else Path(tempfile.mkdtemp(prefix="gcm-"))

# Overrides work as `gcm run --set KEY=VALUE`: here no HTML scene, to stay fast.
pipeline = gcm.Pipeline.from_yaml(ROOT / "configs/bottle_side.yaml", ["publish.html=false"])
result = pipeline.run(out / "bottle", progress=False, force=True)

counts = result.counts
print(f"reachable: {counts['reachable']} of {counts['densified']} grasps")
print(f"unreachable by reason: {counts['unreachable_by_reason']}")

# The best grasps by the config's ranking metric (here `combined`): the grasp
# pose in the world frame (position [m], quaternion w x y z) and the joint
# solution that reaches it [rad].
for grasp in result.top(5):
    pos = ", ".join(f"{grasp[k]:.3f}" for k in ("x", "y", "z"))
    quat = ", ".join(f"{grasp[k]:.3f}" for k in ("qw", "qx", "qy", "qz"))
    q = ", ".join(f"{v:.2f}" for v in grasp["q"])
    print(f"#{grasp['rank']}: p = [{pos}]  q_wxyz = [{quat}]  joints = [{q}]")

print(f"run directory: {result.run_dir}")
