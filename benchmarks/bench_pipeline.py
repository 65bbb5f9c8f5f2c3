#!/usr/bin/env python
"""Reachability stage end to end on the dense bottle manifold, against TRAC-IK in the same run.

Work: ``configs/bottle_side.yaml`` with 80 side grasps and ``subdivisions: 28``
(about 56,000 poses), approach on (10 cm, 10 steps), table and bottle in the
collision world: the reachability stage (:func:`gcm_pipeline.check_reachability`,
the engine of :mod:`gcm_pipeline.reach.engine`: IK, collisions, approach,
re-solves, clearance) timed end to end with ``ik.workers: auto``.

Reference: TRAC-IK (``pytracik``, ``pip install ".[bench]"``), IK only, one
thread, seeded with the home configuration, timeout 5 ms, timed before and
after each stage run in the same run, on two target sets: (a) **the same
poses**: 3,000 poses drawn at random from the dense manifold the stage checks
(what a per-pose TRAC-IK loop over this manifold does; about a sixth of them
have no IK solution and cost TRAC-IK its timeout), and (b) 2,000 reachable
Panda targets (forward kinematics of random configurations, as in
``bench_ik.py``: every one solvable, TRAC-IK's best case). The ratios are the
stage's poses/s over TRAC-IK's targets/s (medians). TRAC-IK is called through
its binding directly (no Python-side quaternion conversion is charged to it).

Correctness in the same run: every reachable row is re-verified by Pinocchio
FK (a fresh ``pin.Data``), the strict joint limits and an independent
collision check (``pin.computeCollisions`` over every pair of the grasp's
world, with contact information on: coal's complete answer, see
:func:`bench_collision.complete_answers`), so the false-positive count is measured, not assumed.

Also reported: the breakdown of the stage's CPU time by step (summed over
workers), peak memory (this process and its workers). ``--million`` adds a
run of about 1,000,000 poses (subdivisions 120) in a fresh process and
reports its peak memory and its cost per pose against the dense run's.

Run from the repository root: ``python benchmarks/bench_pipeline.py``
(a few minutes); writes ``benchmarks/results/pipeline.json``.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import resource
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np
import pinocchio as pin

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))  # run from a clone, no install

from bench_collision import complete_answers  # noqa: E402

from gcm_pipeline import pipeline as P  # noqa: E402
from gcm_pipeline.config import load_config  # noqa: E402
from gcm_pipeline.config.robot_spec import load_robot  # noqa: E402
from gcm_pipeline.geometry.dualquat import dq_to_matrix, quat_from_rotation  # noqa: E402
from gcm_pipeline.pipeline import make_checker  # noqa: E402
from gcm_pipeline.robot.collision import as_transform  # noqa: E402
from gcm_pipeline.robot.model import Robot  # noqa: E402

CONFIG = ROOT / "configs" / "bottle_side.yaml"
DENSE = ["candidates.count=80", "densify.subdivisions=28"]
TOL_P, TOL_R = 1e-4, 1e-3


def peak_rss_mb() -> float:
    """Peak resident memory of this process and of its (finished) children [MB]."""
    me = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    kids = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss
    return (me + kids) / 1024.0


def tracik_rate(robot: Robot, targets: np.ndarray) -> tuple[float, float]:
    """TRAC-IK targets/s (one thread, home seed) and its success rate."""
    import pytracik

    urdf = robot.urdf_path.read_text()
    solver = pytracik.TRAC_IK(
        "panda_link0", robot.grasp_frame, urdf, 0.005, 1e-5, pytracik.SolveType.Speed
    )
    # the binding reads no limits from this URDF: give them (the robot's)
    pytracik.set_joint_limits(solver, robot.lower.tolist(), robot.upper.tolist())
    quats = quat_from_rotation(targets[:, :3, :3]).tolist()  # (w, x, y, z), computed up front
    seed = np.asarray(robot.home, dtype=float)
    ok = 0
    t0 = time.perf_counter()
    for t, (w, x, y, z) in zip(targets, quats, strict=True):
        r = pytracik.ik(solver, seed, t[0, 3], t[1, 3], t[2, 3], x, y, z, w)
        ok += r[0] >= 0
    return len(targets) / (time.perf_counter() - t0), ok / len(targets)


def verify(robot: Robot, cfg: Any, grasps: Any) -> dict[str, int]:
    """Independent re-check of every reachable row: FK, strict limits, every collision pair."""
    rows = np.flatnonzero(np.asarray(grasps["reachable"], dtype=bool))
    q = np.asarray(grasps["q"], dtype=float)[rows]
    base = cfg.robot.base_pose.matrix()
    targets = np.linalg.inv(base) @ dq_to_matrix(np.asarray(grasps["dq"])[rows])
    model = robot.model
    data = model.createData()
    fid = model.getFrameId(robot.grasp_frame)
    checker = make_checker(robot, cfg.environment, cfg.object, base)
    gm = checker.geom_model
    gd = complete_answers(pin.GeometryData(gm))
    bad_fk = bad_limits = bad_collision = 0
    for qi, t in zip(q, targets, strict=True):
        pin.forwardKinematics(model, data, qi)
        pin.updateFramePlacements(model, data)
        m = data.oMf[fid]
        pe = np.linalg.norm(m.translation - t[:3, 3])
        re = np.linalg.norm(pin.log3(t[:3, :3].T @ m.rotation))
        bad_fk += not (pe <= cfg.ik.position_tolerance and re <= cfg.ik.orientation_tolerance)
        bad_limits += not (
            np.all(qi > model.lowerPositionLimit) and np.all(qi < model.upperPositionLimit)
        )
        bad_collision += bool(pin.computeCollisions(model, data, gm, gd, qi, True))
    return {
        "verified_rows": int(rows.size),
        "fk_failures": int(bad_fk),
        "limit_failures": int(bad_limits),
        "collision_failures": int(bad_collision),
        "false_positives": int(bad_fk + bad_limits + bad_collision),
    }


def dense_targets(n: int, rng: np.random.Generator) -> np.ndarray:
    """``n`` poses (4, 4) of the dense manifold's grasp frame in the robot base frame."""
    cfg = load_config(CONFIG, DENSE)
    candidates = P.generate_candidates(cfg)
    grasps = P.densify(candidates, P.build_manifold(candidates, cfg), cfg)
    world = dq_to_matrix(np.asarray(grasps["dq"]))
    base = as_transform(cfg.robot.base_pose)
    rows = rng.choice(len(world), size=min(n, len(world)), replace=False)
    return np.linalg.inv(base) @ world[rows]


def stage_run(overrides: list[str], workers: str, config: Path = CONFIG) -> dict[str, Any]:
    """The reachability stage on the dense bottle manifold: time, result, breakdown.

    ``config``: the run config whose robot and world are used (the Panda's bottle by default).
    """
    cfg = load_config(config, [*overrides, f"ik.workers={workers}"])
    candidates = P.generate_candidates(cfg)
    manifold = P.build_manifold(candidates, cfg)
    grasps = P.densify(candidates, manifold, cfg)
    robot = P.robot_from_config(cfg)
    engine = P.reachability_engine(robot, cfg)
    try:
        t0 = time.perf_counter()
        done = P.check_reachability(grasps, robot, cfg, engine=engine)
        wall = time.perf_counter() - t0
    finally:
        engine.close()
    reasons, counts = np.unique(np.asarray(done["reason"]), return_counts=True)
    return {
        "config": cfg,
        "robot": robot,
        "grasps": done,
        "poses": len(done),
        "wall_s": wall,
        "poses_per_s": len(done) / wall,
        "reachable": int(np.count_nonzero(done["reachable"])),
        "reasons": {str(k) or "reachable": int(v) for k, v in zip(reasons, counts, strict=True)},
        "cpu_s_by_step": {k: round(v, 3) for k, v in engine.timings.items()},
        "workers": engine.workers_used,
    }


def million(path: Path) -> None:
    """Child process: about 1,000,000 poses through the stage; JSON to ``path``."""
    res = stage_run(["candidates.count=80", "densify.subdivisions=120"], "auto")
    out = {k: v for k, v in res.items() if k not in ("config", "robot", "grasps")}
    out["peak_rss_mb"] = peak_rss_mb()
    path.write_text(json.dumps(out, indent=2) + "\n")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--repeats", type=int, default=3, help="stage runs (median)")
    parser.add_argument("--tracik-targets", type=int, default=2000)
    parser.add_argument(
        "--same-targets", type=int, default=3000, help="poses of the dense manifold for TRAC-IK"
    )
    parser.add_argument("--million", action="store_true", help="also run ~1,000,000 poses")
    parser.add_argument("--no-verify", action="store_true", help="skip the independent re-check")
    parser.add_argument("--out", default=str(ROOT / "benchmarks" / "results" / "pipeline.json"))
    parser.add_argument("--million-child", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.million_child:
        million(Path(args.million_child))
        return

    t_start = time.time()
    load_start = os.getloadavg()
    robot = load_robot("panda")
    rng = np.random.default_rng(0)
    targets = robot.fk_pinocchio(robot.random_configurations(args.tracik_targets, rng))

    # (a) the same poses: a random sample of the dense manifold the stage checks
    same = dense_targets(args.same_targets, rng)

    tracik: list[float] = []
    tracik_same: list[float] = []
    runs: list[dict[str, Any]] = []
    for _ in range(max(1, args.repeats)):  # interleaved: the machine's load hits all
        rate, success = tracik_rate(robot, targets)
        tracik.append(rate)
        rate, success_same = tracik_rate(robot, same)
        tracik_same.append(rate)
        runs.append(stage_run(DENSE, "auto"))
    rate, success = tracik_rate(robot, targets)
    tracik.append(rate)
    rate, success_same = tracik_rate(robot, same)
    tracik_same.append(rate)
    walls = [r["wall_s"] for r in runs]
    best = runs[int(np.argsort(walls)[len(walls) // 2])]  # the median run
    stage_rate = best["poses"] / float(np.median(walls))
    tracik_median = float(np.median(tracik))
    same_median = float(np.median(tracik_same))
    one = stage_run(DENSE, "1")  # the same work on one process
    identical = all(
        np.array_equal(np.asarray(one["grasps"][c]), np.asarray(best["grasps"][c]), equal_nan=True)
        for c in ("reachable", "q", "pos_err", "q_pregrasp", "clearance")
    ) and np.array_equal(np.asarray(one["grasps"]["reason"]), np.asarray(best["grasps"]["reason"]))
    report: dict[str, Any] = {
        "work": "bottle_side, 80 side grasps, subdivisions 28, approach 10 cm, table + bottle",
        "poses": best["poses"],
        "workers": best["workers"],
        "stage_wall_s_runs": walls,
        "stage_poses_per_s": stage_rate,
        "stage_poses_per_s_one_process": one["poses_per_s"],
        "tracik_targets_per_s_runs": tracik,
        "tracik_targets_per_s": tracik_median,
        "tracik_success": success,
        "ratio_stage_over_tracik": stage_rate / tracik_median,
        "ratio_stage_one_process_over_tracik": one["poses_per_s"] / tracik_median,
        "tracik_same_poses_targets": len(same),
        "tracik_same_poses_per_s_runs": tracik_same,
        "tracik_same_poses_per_s": same_median,
        "tracik_same_poses_success": success_same,
        "ratio_stage_over_tracik_same_poses": stage_rate / same_median,
        "ratio_stage_one_process_over_tracik_same_poses": one["poses_per_s"] / same_median,
        "reachable": best["reachable"],
        "reasons": best["reasons"],
        "cpu_s_by_step": best["cpu_s_by_step"],
        "one_and_all_workers_identical": bool(identical),
        "peak_rss_mb": peak_rss_mb(),
    }
    if not args.no_verify:
        report["verification"] = verify(best["robot"], best["config"], best["grasps"])
    if args.million:
        child = Path(args.out).with_suffix(".million.json")
        subprocess.run(
            [sys.executable, __file__, "--million-child", str(child)], check=True, cwd=ROOT
        )
        big = json.loads(child.read_text())
        child.unlink()
        big["cost_per_pose_over_dense_run"] = (big["wall_s"] / big["poses"]) / (
            float(np.median(walls)) / best["poses"]
        )
        report["million"] = big
    load_end = os.getloadavg()
    report.update(
        load_average_start=load_start,
        load_average_end=load_end,
        duration_s=time.time() - t_start,
        date_utc=time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
        cores=os.cpu_count(),
        versions={
            "python": platform.python_version(),
            "numpy": np.__version__,
            "pinocchio": pin.__version__,
        },
    )
    r = report
    print(f"dense bottle: {r['poses']:,} poses, workers {r['workers']}")
    print(f"  stage {stage_rate:,.0f} poses/s (median of {len(walls)})")
    print(f"  stage on one process {one['poses_per_s']:,.0f} poses/s")
    print(
        f"  TRAC-IK IK only, {len(same):,} of the same poses: {same_median:,.0f} targets/s "
        f"(one thread), success {100 * success_same:.1f} %"
    )
    print(
        f"  ratio vs the same poses {r['ratio_stage_over_tracik_same_poses']:.2f}x, "
        f"one process {r['ratio_stage_one_process_over_tracik_same_poses']:.2f}x"
    )
    print(
        f"  TRAC-IK IK only, {len(targets):,} random reachable targets: {tracik_median:,.0f} "
        f"targets/s (one thread), success {100 * success:.1f} %"
    )
    print(
        f"  ratio vs reachable targets {r['ratio_stage_over_tracik']:.2f}x, "
        f"one process {r['ratio_stage_one_process_over_tracik']:.2f}x"
    )
    print(f"  reachable {r['reachable']:,}; {r['reasons']}")
    print(f"  CPU by step [s]: {r['cpu_s_by_step']}")
    print(f"  1 and {r['workers']} workers identical: {r['one_and_all_workers_identical']}")
    if "verification" in r:
        print(f"  independent re-check: {r['verification']}")
    print(f"  peak memory {r['peak_rss_mb']:.0f} MB")
    if "million" in r:
        m = r["million"]
        print(f"1M run: {m['poses']:,} poses, {m['poses_per_s']:,.0f} poses/s")
        print(f"  peak memory {m['peak_rss_mb']:.0f} MB")
        print(f"  cost per pose {m['cost_per_pose_over_dense_run']:.2f}x the dense run's")
    print(f"load average at start {load_start[0]:.2f}, at end {load_end[0]:.2f}")
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(report, indent=2, default=str) + "\n")
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
