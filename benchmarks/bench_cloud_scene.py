"""A Contact-GraspNet scene end to end: the rate with the cloud as an obstacle, and a raw check.

Run from the repository root::

    python benchmarks/bench_cloud_scene.py                 # writes results/cloud_scene.json
    python benchmarks/bench_cloud_scene.py --repeats 1 --config my_scene.yaml
    python benchmarks/bench_cloud_scene.py --stages big.npy   # writes results/cloud_stages.json

Scenes: ``configs/clutter_scene.yaml`` (the committed rendered scene,
``tests/data/clutter``: Contact-GraspNet-layout predictions of a mug on a
cluttered table, the rest of the scene a depth-image cloud) and every
``--config`` given, e.g. one of Contact-GraspNet's own test scenes. Those are
not in the repository (NVIDIA Source Code License, non-commercial): scene
``test_data/7.npy`` of NVlabs/contact_graspnet (``depth``, ``K``, ``rgb``)
with the predictions ``results/predictions_7.npz`` of
github.com/FrankJIE09/contact_graspnet (commit c6ec21a) and a camera pose that
puts the table plane fitted to the cloud at z = 0, e.g.::

    candidates: {source: file, path: predictions_7.npz, format: contact_graspnet,
                 camera_pose: {xyz: [-0.1818, 0.0961, 0.6647],
                               rpy_deg: [-122.138, -0.394, -89.752]}}
    environment:
      table: {height: 0.0}
      point_clouds: [{path: 7.npy, voxel_size: 0.01, max_depth: 1.5,
                      crop_min: [-2, -2, 0.01], name: scene7}]

Per scene, the run is timed with the cloud and without it (``point_clouds:
[]``) in this process, one worker, no plots or scene (median of
``--repeats``): poses analysed per second of the reachability stage and of
the whole run, and the ratio without / with the cloud. Then, independently
of the package's cloud reader, voxel grid, tiles and broad phase, every
reachable grasp's configuration is checked against the raw depth points:
the depth image is back-projected here (``K``, the camera pose, the config's
``max_depth``, crop and excluded segments), an octree of the raw points at the
voxel size is built by coal, and each robot collision geometry placed by
Pinocchio's forward kinematics is tested with ``coal.collide``
(``raw_check_collisions``: the count of reachable grasps that touch it; the
target is 0).

``--stages CLOUD`` (an (N, 3) ``.npy`` or ``.ply`` of world points, e.g. a fused scan
of millions) instead times each stage of the bottle example
(``configs/bottle_side.yaml``, its table left to the cloud, 5 mm voxels, the points
within 1 cm of the bottle dropped) in this process, one worker: reading and
voxelising the cloud, building its octree tiles, building the reachability engine
(tiles and checker), the stage's steps (CPU s), and the peak resident memory.
Then the clearance of the stage's reachable configurations twice on one checker:
coal over the cells near each link (as the stage does) and coal over whole tiles
(the reference, ``--reference-rows`` rows), with the ratio and the largest
difference of their answers.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import resource
import statistics
import sys
import time
from pathlib import Path

import coal
import numpy as np
import pinocchio as pin

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from gcm_pipeline.config import load_config  # noqa: E402
from gcm_pipeline.config.robot_spec import load_robot  # noqa: E402
from gcm_pipeline.pipeline import Pipeline  # noqa: E402

QUIET = ["publish.html=false", "publish.plots=false", "ik.workers=1"]


def _timed(config: Path, overrides: list[str], out: Path, repeats: int) -> dict:
    """Median stage and total times of ``repeats`` runs, and the last run's counts."""
    stage, total = [], []
    for _ in range(repeats):
        cfg = load_config(config, [*QUIET, *overrides])
        t0 = time.perf_counter()
        result = Pipeline(cfg).run(out, progress=False, force=True)
        total.append(time.perf_counter() - t0)
        stage.append(result.timings["reachability"])
    n = result.counts["densified"]
    return {
        "poses": n,
        "reachable": result.counts["reachable"],
        "unreachable_by_reason": result.counts["unreachable_by_reason"],
        "reachability_s": statistics.median(stage),
        "total_s": statistics.median(total),
        "poses_per_s_stage": n / statistics.median(stage),
        "poses_per_s_total": n / statistics.median(total),
    }


def _scene_arrays(path: Path) -> dict:
    """``depth``, ``K`` and optional ``segmap`` of a Contact-GraspNet scene (.npz or .npy)."""
    if path.suffix == ".npz":
        data = dict(np.load(path))
    else:
        data = np.load(path, allow_pickle=True).item()  # a trusted file named by the user
    seg = data.get("segmap", data.get("seg"))
    return {"depth": np.asarray(data["depth"], float), "K": np.asarray(data["K"]), "segmap": seg}


def _raw_points(cfg) -> tuple[np.ndarray, float]:
    """The first cloud's raw depth points in the robot's base frame, and its voxel size."""
    pc = cfg.environment.point_clouds[0]
    scene = _scene_arrays(Path(pc.path))
    depth, k, seg = scene["depth"], scene["K"], scene["segmap"]
    keep = np.isfinite(depth) & (depth > 0)
    if pc.max_depth is not None:
        keep &= depth <= pc.max_depth
    if seg is not None and pc.exclude_segments:
        keep &= ~np.isin(seg, pc.exclude_segments)
    v, u = np.nonzero(keep)
    z = depth[v, u]
    cam = np.stack([(u - k[0, 2]) * z / k[0, 0], (v - k[1, 2]) * z / k[1, 1], z], axis=1)
    pose = (pc.camera_pose or cfg.candidates.camera_pose).matrix()
    world = cam @ pose[:3, :3].T + pose[:3, 3]
    lo = np.array(pc.crop_min) if pc.crop_min is not None else np.full(3, -np.inf)
    hi = np.array(pc.crop_max) if pc.crop_max is not None else np.full(3, np.inf)
    world = world[np.all((world >= lo) & (world <= hi), axis=1)]
    base = np.linalg.inv(cfg.robot.base_pose.matrix())
    return world @ base[:3, :3].T + base[:3, 3], pc.voxel_size


def _raw_check(cfg, run_dir: Path) -> dict:
    """Reachable grasps whose robot touches an octree of the raw points (plain coal)."""
    import csv

    with open(run_dir / "grasps.csv", newline="") as fh:
        reachable = np.array([r["reachable"] == "true" for r in csv.DictReader(fh)])
    q = np.load(run_dir / "configurations.npz")["q"][reachable]
    points, voxel = _raw_points(cfg)
    tree = coal.makeOctree(points, voxel)
    robot = load_robot(cfg.robot.spec, cfg.robot.tool)
    model, gm = robot.model, robot.build_geometry("collision")
    data, gd = model.createData(), pin.GeometryData(gm)
    identity = coal.Transform3s(np.eye(3), np.zeros(3))
    touching = 0
    t0 = time.perf_counter()
    for qi in q:
        pin.forwardKinematics(model, data, qi)
        pin.updateGeometryPlacements(model, data, gm, gd)
        for g, go in enumerate(gm.geometryObjects):
            m = gd.oMg[g]
            req, res = coal.CollisionRequest(), coal.CollisionResult()
            if coal.collide(
                go.geometry, coal.Transform3s(m.rotation, m.translation), tree, identity, req, res
            ):
                touching += 1
                break
    return {
        "raw_points": int(len(points)),
        "reachable_checked": int(len(q)),
        "raw_check_collisions": touching,
        "raw_check_s": time.perf_counter() - t0,
    }


def _clock(fn):
    """``fn()``, its wall and CPU seconds."""
    t0, c0 = time.perf_counter(), time.process_time()
    value = fn()
    return value, {"wall_s": time.perf_counter() - t0, "cpu_s": time.process_time() - c0}


def _stages(cloud: Path, reference_rows: int) -> dict:
    """Stage times of the bottle example with ``cloud`` as its scene (see the module doc)."""
    from gcm_pipeline import pipeline as P
    from gcm_pipeline.pipeline.clouds import cloud_world, scene_clouds

    cfg = load_config(
        REPO / "configs/bottle_side.yaml",
        [
            "environment.table=null",
            f"environment.point_clouds=[{{path: {cloud}, frame: world, voxel_size: 0.005, "
            "exclude_object_distance: 0.01, name: scene}]",
            "ik.workers=1",
        ],
    )
    cands = P.generate_candidates(cfg)
    grasps = P.densify(cands, P.build_manifold(cands, cfg), cfg)
    robot = P.robot_from_config(cfg)
    clouds, load = _clock(lambda: scene_clouds(cfg.environment, cfg.object))
    base_inv = np.linalg.inv(cfg.robot.base_pose.matrix())
    tiles, build = _clock(lambda: cloud_world(cfg.environment, cfg.object, base_inv))
    engine, engine_s = _clock(lambda: P.reachability_engine(robot, cfg))
    done, stage = _clock(lambda: P.check_reachability(grasps, robot, cfg, engine=engine))
    checker = P.make_checker(robot, cfg.environment, cfg.object, cfg.robot.base_pose)
    engine.close()
    q = np.asarray(done["q"])[np.asarray(done["reachable"], bool)][:reference_rows]
    near, near_s = _clock(lambda: checker.clearance(q))
    octree_pairs, checker._octree_pairs = checker._octree_pairs, {}  # coal on whole tiles
    whole, whole_s = _clock(lambda: checker.clearance(q))
    checker._octree_pairs = octree_pairs
    return {
        "points": int(sum(c.counts["read"] for c in clouds)),
        "voxels": int(sum(len(c) for c in clouds)),
        "tiles": len(tiles),
        "poses": len(done),
        "reachable": int(np.count_nonzero(done["reachable"])),
        "load_voxelise": load,
        "octree_build": build,
        "engine_build": engine_s,
        "reachability": stage,
        "reachability_steps_cpu_s": dict(engine.timings),
        "peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
        "clearance_reference": {
            "rows": int(len(q)),
            "near_cells_cpu_s": near_s["cpu_s"],
            "whole_tiles_cpu_s": whole_s["cpu_s"],
            "speedup": whole_s["cpu_s"] / max(near_s["cpu_s"], 1e-9),
            "max_abs_difference_m": float(np.max(np.abs(near - whole), initial=0.0)),
        },
    }


def _print_stages(s: dict) -> None:
    print(
        f"{s['points']:,} points -> {s['voxels']:,} voxels in {s['tiles']} tiles; "
        f"{s['poses']} poses, {s['reachable']} reachable; peak {s['peak_rss_mb']:.0f} MB"
    )
    for key in ("load_voxelise", "octree_build", "engine_build", "reachability"):
        print(f"  {key:15s} {s[key]['wall_s']:8.2f} s wall {s[key]['cpu_s']:8.2f} s CPU")
    for key, value in s["reachability_steps_cpu_s"].items():
        print(f"    {key:13s} {value:8.2f} s CPU")
    ref = s["clearance_reference"]
    print(
        f"  clearance of {ref['rows']} reachable rows: near cells {ref['near_cells_cpu_s']:.2f} s, "
        f"whole tiles {ref['whole_tiles_cpu_s']:.2f} s CPU (x{ref['speedup']:.1f}), "
        f"largest difference {ref['max_abs_difference_m']:.3g} m"
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--config", action="append", type=Path, default=[])
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--out", type=Path, default=None)
    parser.add_argument("--work", type=Path, default=Path("/tmp/gcm_bench_cloud_scene"))
    parser.add_argument("--stages", type=Path, help="time the stages on this cloud instead")
    parser.add_argument("--reference-rows", type=int, default=60)
    args = parser.parse_args()
    if args.stages is not None:
        out = args.out or REPO / "benchmarks/results/cloud_stages.json"
        stages = _stages(args.stages.resolve(), args.reference_rows)
        _print_stages(stages)
        report = {
            "command": f"python benchmarks/bench_cloud_scene.py --stages {args.stages.name}"
            f" --reference-rows {args.reference_rows}",
            "python": platform.python_version(),
            "machine": platform.machine(),
            "date_utc": time.strftime("%Y-%m-%d %H:%M", time.gmtime()),
            "load_average": os.getloadavg()[0],
            **stages,
        }
        out.parent.mkdir(parents=True, exist_ok=True)
        out.write_text(json.dumps(report, indent=2) + "\n")
        print(f"wrote {out}")
        return
    args.out = args.out or REPO / "benchmarks/results/cloud_scene.json"
    report: dict = {
        "command": "python benchmarks/bench_cloud_scene.py"
        + "".join(f" --config {c.name}" for c in args.config)
        + f" --repeats {args.repeats}",
        "python": platform.python_version(),
        "machine": platform.machine(),
    }
    scenes = {}
    for config in [REPO / "configs/clutter_scene.yaml", *args.config]:
        name = config.stem
        cfg = load_config(config, QUIET)
        with_cloud = _timed(config, [], args.work / name, args.repeats)
        without = _timed(
            config, ["environment.point_clouds=[]"], args.work / f"{name}_no_cloud", args.repeats
        )
        check = _raw_check(cfg, args.work / name)
        scene = {
            "with_cloud": with_cloud,
            "without_cloud": without,
            "stage_ratio_without_over_with": without["poses_per_s_stage"]
            / with_cloud["poses_per_s_stage"],
            **check,
        }
        scenes[name] = scene
        print(
            f"{name}: {with_cloud['poses']} poses, reachable {with_cloud['reachable']} with the "
            f"cloud / {without['reachable']} without; stage {with_cloud['poses_per_s_stage']:,.0f}"
            f" poses/s with the cloud, {without['poses_per_s_stage']:,.0f} without "
            f"(x{scene['stage_ratio_without_over_with']:.1f}); whole run "
            f"{with_cloud['poses_per_s_total']:,.0f} poses/s; raw check: "
            f"{check['raw_check_collisions']} of {check['reachable_checked']} reachable grasps "
            f"touch the {check['raw_points']:,} raw points"
        )
    report["scenes"] = scenes
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(report, indent=2) + "\n")
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
