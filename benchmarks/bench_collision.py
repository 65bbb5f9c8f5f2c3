"""Benchmark: collision checks per second and the cost of the approach check per grasp.

World: the Panda (example-robot-data, fingers open) at the origin, the default
table (top at z = 0) and the bottle of ``configs/bottle_side.yaml`` (cylinder
r = 3.5 cm, h = 22 cm at x = 0.5 m).

* ``check``: :meth:`CollisionChecker.check` on random in-limit configurations
  whose grasp frame is in front of the robot and above the table
  (x > 0.2 m, z > 0.02 m): the kind an IK returns for grasps on the table.
* ``pinocchio_loop``: the speed reference, ``pin.computeCollisions`` in a Python
  loop over the same configurations with every pair (stop at first collision),
  timed with Pinocchio's default requests. Its answers are not the truth: without
  contact information coal's ``collide`` can call overlapping geometry free (GJK
  ending within its tolerance of the origin). The checker is compared with the
  same loop asking coal's complete answer instead (contact information on:
  :func:`complete_answers`), untimed; ``*pinocchio_default_missed`` counts the
  configurations the timed loop called free that the complete answer finds
  colliding. The two can differ only within about a micrometre of contact (the
  checker counts geometry within 1e-6 m as touching; coal's complete answer
  called some pairs 1.0-1.4e-6 m apart colliding), where random configurations
  do not fall.
* ``clearance``: :meth:`CollisionChecker.clearance` on the same configurations.
* ``approach``: :func:`~gcm_pipeline.reach.move_check.check_moves` (10 steps over 10 cm) for IK
  solutions of top-down grasps over the table, per grasp.
* ``check_mesh``: the same configurations against a thin-walled mesh object instead of
  the bottle (the mug of ``configs/data/mug.obj``, 3 mm wall, 784 triangles, at the
  bottle's place): the contact model erodes the gripper's pieces and tests whether a
  piece lies inside the mesh (see :mod:`gcm_pipeline.robot.collision.contact`); the reference is
  Pinocchio's loop over the same pairs (which lacks the inside test; timed and
  compared as above).
* ``check_cloud``: the same configurations with a cluttered scene as a 100k-point cloud
  (surfaces of eight boxes, cylinders and spheres around the bottle, sampled) added as
  ``environment.point_clouds`` (1 cm voxels, coal octree tiles); ``cloud_read_s`` reads
  and voxelises the ``.npy``; the reference is Pinocchio's loop over the same pairs
  (timed and compared as above), and the checker must agree with coal's complete
  answer on every configuration. ``ratios`` compares the rates
  of one run (the machine is shared: rates of different runs are not comparable).

The machine is shared: every figure is the median of ``--repeats`` runs.

Run: ``python benchmarks/bench_collision.py`` (writes ``benchmarks/results/collision.json``).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import pinocchio as pin
import trimesh

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # run from a clone, no install

from gcm_pipeline.config import EnvironmentConfig, ObjectConfig
from gcm_pipeline.config.robot_spec import load_robot
from gcm_pipeline.pipeline import make_checker
from gcm_pipeline.pipeline.clouds import cloud_options, scene_clouds
from gcm_pipeline.reach.deviation import gripper_radius
from gcm_pipeline.reach.move_check import check_moves
from gcm_pipeline.reach.moves import Move
from gcm_pipeline.robot.collision.clouds import octree
from gcm_pipeline.robot.ik import solve_ik
from gcm_pipeline.sources.clouds import read_cloud

MUG = Path(__file__).resolve().parents[1] / "configs" / "data" / "mug.obj"
BOTTLE = {
    "shape": "cylinder",
    "dims": {"radius": 0.035, "height": 0.22},
    "pose": {"xyz": [0.5, 0.0, 0.0]},
}


def front_configurations(robot, n: int, seed: int = 0) -> np.ndarray:
    """Random in-limit configurations with the grasp frame in front of the robot."""
    rng = np.random.default_rng(seed)
    out = []
    while sum(len(o) for o in out) < n:
        q = robot.random_configurations(4 * n, rng)
        p = robot.fk(q)[:, :3, 3]
        out.append(q[(p[:, 0] > 0.2) & (p[:, 2] > 0.02)])
    return np.concatenate(out)[:n]


def top_down_grasps(n: int, seed: int = 0) -> np.ndarray:
    """Top-down grasp poses over the table in front of the robot (N, 4, 4)."""
    rng = np.random.default_rng(seed)
    out = np.zeros((n, 4, 4))
    yaw = rng.uniform(-np.pi / 2, np.pi / 2, n)
    c, s = np.cos(yaw), np.sin(yaw)
    # z down, x/y rotated by yaw about the vertical
    out[:, 0, 0], out[:, 1, 0] = c, s
    out[:, 0, 1], out[:, 1, 1] = s, -c
    out[:, 2, 2] = -1.0
    out[:, 0, 3] = rng.uniform(0.3, 0.6, n)
    out[:, 1, 3] = rng.uniform(-0.3, 0.3, n)
    out[:, 2, 3] = rng.uniform(0.05, 0.3, n)
    out[:, 3, 3] = 1.0
    return out


def clutter_cloud(path: Path, n: int = 100_000, seed: int = 0) -> None:
    """Write ``n`` points sampled on eight objects around the bottle to ``path`` (.npy)."""
    rng = np.random.default_rng(seed)
    meshes = []
    for i, (x, y) in enumerate(
        [
            (0.35, -0.25),
            (0.4, 0.25),
            (0.55, -0.2),
            (0.6, 0.2),
            (0.7, -0.05),
            (0.7, 0.3),
            (0.35, 0.1),
            (0.65, -0.35),
        ]
    ):
        h = rng.uniform(0.08, 0.3)
        if i % 3 == 0:
            m = trimesh.creation.box((rng.uniform(0.04, 0.1), rng.uniform(0.04, 0.1), h))
            m.apply_translation((0, 0, h / 2))
        elif i % 3 == 1:
            m = trimesh.creation.cylinder(rng.uniform(0.02, 0.05), h)
            m.apply_translation((0, 0, h / 2))
        else:
            m = trimesh.creation.icosphere(3, rng.uniform(0.03, 0.06))
            m.apply_translation((0, 0, 0.06))
        m.apply_translation((x, y, 0.0))
        meshes.append(m)
    scene = trimesh.util.concatenate(meshes)
    np.save(path, np.asarray(scene.sample(n, seed=seed)))


def complete_answers(gd):
    """``gd`` (a ``pin.GeometryData``) asking coal for its complete answer: contact on.

    With contact information EPA runs whenever GJK finds contact; Pinocchio's
    default requests ask without it, and coal's ``collide`` then can call
    overlapping geometry free (GJK ending within its tolerance of the origin,
    at any depth). Written here, not the checker's requests: the reference
    shares no code with the checker's narrow phase.
    """
    for req in gd.collisionRequests:
        req.enable_contact = True
    return gd


def complete_hits(model, gm, q: np.ndarray) -> np.ndarray:
    """coal's complete answer through Pinocchio's loop (every pair of ``gm``): (N,) collides."""
    data, gd = model.createData(), complete_answers(pin.GeometryData(gm))
    return np.array([pin.computeCollisions(model, data, gm, gd, qi, True) for qi in q])


def timed(fn, repeats: int) -> tuple[float, object]:
    times, out = [], None
    for _ in range(repeats):
        t0 = time.perf_counter()
        out = fn()
        times.append(time.perf_counter() - t0)
    return statistics.median(times), out


def cloud_results(robot, obj, q, m, args, results) -> None:
    """The ``check_cloud`` figures (see the module doc)."""
    n = len(q)
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "clutter.npy"
        clutter_cloud(path)
        env = EnvironmentConfig.model_validate(
            {"point_clouds": [{"path": str(path), "frame": "world", "voxel_size": 0.01}]}
        )
        dt, cloud = timed(
            lambda: read_cloud(cloud_options(0, env.point_clouds[0], obj, None)), args.repeats
        )
        results["cloud_points"] = cloud.counts["read"]
        results["cloud_voxels"] = cloud.counts["voxels"]
        results["cloud_read_s"] = dt
        dt, _ = timed(lambda: octree(cloud.points, 0.01), args.repeats)
        results["cloud_octree_build_s"] = dt
        scene_clouds(env, obj)  # read once (kept), as a run does
        t0 = time.perf_counter()
        checker = make_checker(robot, env, obj)
        results["cloud_checker_build_s"] = time.perf_counter() - t0
    results["cloud_tiles"] = sum(s.name.startswith("cloud_0_") for s in checker.world)
    dt, reasons = timed(lambda: checker.check(q), args.repeats)
    results["check_cloud_threads1_per_s"] = n / dt
    kinds, counts = np.unique(np.asarray(reasons), return_counts=True)
    results["cloud_reasons"] = {
        str(k) or "free": int(v) for k, v in zip(kinds, counts, strict=True)
    }
    model, gm = robot.model, checker.geom_model
    data, gd = model.createData(), pin.GeometryData(gm)

    def loop() -> np.ndarray:
        return np.array([pin.computeCollisions(model, data, gm, gd, qi, True) for qi in q[:m]])

    dt, fast = timed(loop, args.repeats)
    results["cloud_pinocchio_loop_per_s"] = m / dt
    hit = complete_hits(model, gm, q[:m])
    results["cloud_pinocchio_default_missed"] = int(np.count_nonzero(hit & ~np.asarray(fast)))
    assert np.array_equal(hit, np.asarray(reasons)[:m] != ""), "checker disagrees with coal"
    rate = results["check_cloud_threads1_per_s"]
    results["ratios"] = {
        "cloud_vs_primitives": rate / results["check_threads1_per_s"],
        "cloud_vs_mesh": rate / results["check_mesh_threads1_per_s"],
        "cloud_vs_pinocchio_loop": rate / results["cloud_pinocchio_loop_per_s"],
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--configs", type=int, default=20000)
    parser.add_argument("--grasps", type=int, default=500)
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument(
        "--out", type=Path, default=Path(__file__).parent / "results" / "collision.json"
    )
    args = parser.parse_args()

    robot = load_robot("panda")
    obj = ObjectConfig.model_validate(BOTTLE)
    t0 = time.perf_counter()
    checker = make_checker(robot, EnvironmentConfig(), obj)
    build_s = time.perf_counter() - t0
    q = front_configurations(robot, args.configs)
    n = len(q)
    results: dict[str, object] = {"configurations": n, "checker_build_s": build_s}

    for threads in (1, 2):
        c = checker if threads == 1 else make_checker(robot, EnvironmentConfig(), obj, threads=2)
        dt, reasons = timed(lambda c=c: c.check(q), args.repeats)
        results[f"check_threads{threads}_per_s"] = n / dt
    kinds, counts = np.unique(np.asarray(reasons), return_counts=True)
    results["reasons"] = {str(k) or "free": int(v) for k, v in zip(kinds, counts, strict=True)}

    model, gm = robot.model, checker.geom_model
    data, gd = model.createData(), pin.GeometryData(gm)
    m = min(n, 5000)

    def loop() -> np.ndarray:
        return np.array([pin.computeCollisions(model, data, gm, gd, qi, True) for qi in q[:m]])

    dt, fast = timed(loop, args.repeats)
    results["pinocchio_loop_per_s"] = m / dt
    hit = complete_hits(model, gm, q[:m])
    results["pinocchio_default_missed"] = int(np.count_nonzero(hit & ~np.asarray(fast)))
    assert np.array_equal(hit, np.asarray(reasons)[:m] != ""), "checker disagrees with coal"

    k = min(n, 2000)
    dt, _ = timed(lambda: checker.clearance(q[:k]), max(1, args.repeats // 2))
    results["clearance_per_s"] = k / dt

    grasps = top_down_grasps(args.grasps)
    ik = solve_ik(robot, grasps, validator=checker.check)
    ok = ik.success
    move = Move(distance=0.10, direction=(0, 0, -1), frame="grasp", steps=10)
    radius = gripper_radius(robot)
    dt, res = timed(
        lambda: check_moves(
            robot,
            grasps[ok],
            ik.q[ok],
            move,
            lambda qs, rows: checker.check(qs, mode="approach"),
            gripper_radius=radius,
        ),
        max(1, args.repeats // 2),
    )
    results["approach_grasps"] = int(ok.sum())
    results["approach_s_per_grasp"] = dt / max(1, int(ok.sum()))
    results["approach_grasps_per_s"] = int(ok.sum()) / dt
    results["approach_passed"] = int(np.count_nonzero(res.ok))
    mug = ObjectConfig.model_validate(
        {"shape": "mesh", "mesh": str(MUG), "pose": {"xyz": [0.5, 0.0, 0.0]}}
    )
    t0 = time.perf_counter()
    mesh_checker = make_checker(robot, EnvironmentConfig(), mug)
    results["mesh_checker_build_s"] = time.perf_counter() - t0
    dt, mesh_reasons = timed(lambda: mesh_checker.check(q), args.repeats)
    results["check_mesh_threads1_per_s"] = n / dt
    kinds, counts = np.unique(np.asarray(mesh_reasons), return_counts=True)
    results["mesh_reasons"] = {str(k) or "free": int(v) for k, v in zip(kinds, counts, strict=True)}
    gm2 = mesh_checker.geom_model
    gd2 = pin.GeometryData(gm2)

    def mesh_loop() -> np.ndarray:
        return np.array([pin.computeCollisions(model, data, gm2, gd2, qi, True) for qi in q[:m]])

    dt, fast2 = timed(mesh_loop, args.repeats)
    results["mesh_pinocchio_loop_per_s"] = m / dt
    hit2 = complete_hits(model, gm2, q[:m])
    results["mesh_pinocchio_default_missed"] = int(np.count_nonzero(hit2 & ~np.asarray(fast2)))
    # every pair coal finds is found; the inside test may find more
    assert np.all(np.asarray(mesh_reasons)[:m][hit2] != ""), "checker misses a mesh collision"
    results["mesh_inside_only"] = int(
        np.count_nonzero((np.asarray(mesh_reasons)[:m] != "") & ~hit2)
    )
    cloud_results(robot, obj, q, m, args, results)
    results["machine"] = {
        "cpu_count": os.cpu_count(),
        "python": platform.python_version(),
        "pinocchio": pin.__version__,
    }
    results["target_checks_per_s"] = 5000
    for key, value in results.items():
        print(f"{key:28s} {value:.6g}" if isinstance(value, float) else f"{key:28s} {value}")
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(results, indent=2) + "\n", encoding="utf-8")
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
