"""A tiny placement study on Ray: where should the bottle stand?

    python examples/03_study.py [OUT_DIR]

Each placement is the base config with `--set` overrides of the object pose;
Ray runs them in parallel on this machine (started and stopped for the study).
"""

import sys
import tempfile
from pathlib import Path

import numpy as np

import gcm_pipeline as gcm

ROOT = Path(__file__).resolve().parent.parent
out = Path(sys.argv[1]) if len(sys.argv) > 1 else Path(tempfile.mkdtemp(prefix="gcm-"))

study = gcm.Study.from_dict(
    {
        "base": str(ROOT / "configs/bottle_side.yaml"),
        # fewer grasps and no per-placement scene: small and fast
        "set": ["candidates.count=18", "manifold.max_edge_length=0.15", "publish.html=false"],
        # 2 x 2 = 4 placements of the bottle in front of the robot
        "sweep": {"object_pose": {"x": [0.35, 0.55], "yaw_deg": [0, 20]}},
    }
)
for placement in study.placements():
    print("placement:", placement.overrides)

# Local Ray with two workers; rerunning with the same directory resumes.
result = study.run(out / "study", workers=2, progress=False)

for row in result.rows:
    print(
        f"x = {row['object_x']:.2f} m, yaw = {row['object_yaw_deg']:>4.0f} deg: "
        f"{row['reachable']} of {row['densified']} grasps reachable"
    )
print(f"best: x = {result.best['object_x']:.2f} m, yaw = {result.best['object_yaw_deg']:.0f} deg")

# placements x grasps: which grasps are reachable at every placement?
with np.load(result.out_dir / "reachability.npz") as r:
    everywhere = r["reachable"].all(axis=0)
    print(f"{int(everywhere.sum())} of {int(r['n_grasps'].max())} grasps reachable everywhere")
print(f"study directory: {result.out_dir}")
