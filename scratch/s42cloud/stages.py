"""Stage times, peak memory and the answers of the cloud scene (one worker, one process).

    cd TREE && PYTHONPATH=TREE python scratch/s42cloud/stages.py CLOUD.npy OUT.pkl [--set K=V ...]

Prints JSON: wall and CPU s of reading + voxelising the cloud, building its octree tiles,
building the reachability engine (octrees again + checker), the stage's own steps
(engine.timings, CPU s), and the peak RSS; OUT.pkl holds the stage's result columns.
"""

import json
import pickle
import resource
import sys
import time
from pathlib import Path

import numpy as np

from gcm_pipeline import pipeline as P
from gcm_pipeline.config import load_config
from gcm_pipeline.pipeline.clouds import cloud_world, scene_clouds

here = Path(__file__).resolve().parent
cloud, out = sys.argv[1], sys.argv[2]
extra = [a for a in sys.argv[3:] if a != "--set"]
cfg = load_config(
    here / "cloud_scene.yaml", [f"environment.point_clouds.0.path={cloud}", "ik.workers=1", *extra]
)
rep = {}


def timed(name, fn):
    """``fn()``, its wall and CPU seconds kept in the report under ``name``."""
    t0, c0 = time.perf_counter(), time.process_time()
    v = fn()
    rep[name] = {
        "wall": round(time.perf_counter() - t0, 3),
        "cpu": round(time.process_time() - c0, 3),
    }
    return v


cands = P.generate_candidates(cfg)
grasps = P.densify(cands, P.build_manifold(cands, cfg), cfg)
robot = P.robot_from_config(cfg)
clouds = timed("load_voxelise", lambda: scene_clouds(cfg.environment, cfg.object, None))
rep["voxels"] = int(sum(len(c) for c in clouds))
base_inv = np.linalg.inv(cfg.robot.base_pose.matrix())
tiles = timed("octree_build", lambda: cloud_world(cfg.environment, cfg.object, base_inv))
rep["tiles"] = len(tiles)
del tiles
eng = timed("engine_build", lambda: P.reachability_engine(robot, cfg))
done = timed("reachability", lambda: P.check_reachability(grasps, robot, cfg, engine=eng))
eng.close()
rep["steps_cpu"] = {k: round(v, 3) for k, v in eng.timings.items()}
rep["poses"] = len(done)
rep["reachable"] = int(np.count_nonzero(done["reachable"]))
rep["peak_rss_mb"] = round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024)
print(json.dumps(rep))
pickle.dump({c: np.asarray(done[c]) for c in done.columns}, open(out, "wb"))
