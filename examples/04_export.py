"""Export a run's grasps for other tools: MoveIt grasp messages and Parquet.

    python examples/04_export.py [OUT_DIR]

The same as `gcm export RUN_DIR --format moveit|parquet|npz [--top N]`.
"""

import sys
import tempfile
from pathlib import Path

import pyarrow.parquet as pq
import yaml

import gcm_pipeline as gcm

ROOT = Path(__file__).resolve().parent.parent
out = Path(sys.argv[1]) if len(sys.argv) > 1 else Path(tempfile.mkdtemp(prefix="gcm-"))

# A small run: three grasps on a flat surface, densified.
run = gcm.Pipeline.from_yaml(ROOT / "configs/flat_surface.yaml", ["publish.html=false"])
run_dir = run.run(out / "flat", progress=False, force=True).run_dir
print(f"run directory: {run_dir}")

# The 10 best grasps as moveit_msgs/Grasp messages (ROS 2 field names), best first.
moveit = gcm.export_run(run_dir, "moveit", top=10, out=out / "grasps_moveit.yaml")
grasps = yaml.safe_load(moveit.path.read_text())
first = grasps[0]["grasp_pose"]
print(f"{moveit.path.name}: {moveit.rows} grasps; the best in frame {first['header']['frame_id']}:")
print("  position", first["pose"]["position"], "quality", grasps[0]["grasp_quality"])

# Every grasp (reachable or not) as a Parquet table for pandas, polars or DuckDB.
table = gcm.export_run(run_dir, "parquet", out=out / "grasps.parquet")
columns = pq.read_table(table.path)
print(f"{table.path.name}: {columns.num_rows} rows, columns {columns.column_names[:8]} ...")
reachable = sum(columns.column("reachable").to_pylist())
print(f"  reachable rows: {reachable}")
