#!/usr/bin/env python
"""IK benchmark: recall, false positives and throughput of the IK backends (Panda).

Target sets (fixed seed):

* ``reachable``: 2,000 poses, forward kinematics (Pinocchio) of uniformly random
  joint configurations inside the limits;
* ``unreachable``: 500 poses with random orientations at 1.3-2.0 m from the
  shoulder (the reach pre-filter rejects them before any IK runs);
* ``unreachable_near``: 500 poses at 0.75-0.94 m from the shoulder, inside the
  arm's reach (0.949 m for the Panda) but with the approach axis pointing back
  at the shoulder (the hand would have to reach back past its own wrist): the
  Panda's reach proof (the wrist beyond the elbow's range whatever joint 7 is)
  rejects them before any seed; an arm without it runs the IK, which must fail.

For each backend: recall on ``reachable``; false positives = successes on the
unreachable sets plus successes that fail an independent re-check (a fresh
``pin.Data``, ``pin.forwardKinematics`` + ``updateFramePlacements``,
``pin.log3`` and the joint limits); targets/s with one process and with all
cores (``workers``), medians of several repeats (wall clock; the CPU-time rate
of the one-process run is printed too because the machine may be shared).
mink runs on a subset (``--mink-targets``, default 200 reachable targets) to
keep the run short. TRAC-IK (``pytracik``, ``pip install ".[bench]"``) runs on
the same 2,000 reachable targets in the same run (one thread, home seed), and
the default backend's rates are reported as ratios to it. Also times the
manipulability of 100,000 configurations.

Run from the repository root: ``python benchmarks/bench_ik.py``; writes
``benchmarks/results/ik.json``.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np
import pinocchio as pin
from scipy.spatial.transform import Rotation

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from gcm_pipeline.config.robot_spec import load_robot  # noqa: E402
from gcm_pipeline.robot.ik import solve_ik  # noqa: E402
from gcm_pipeline.robot.manipulability import manipulability_metrics, yoshikawa  # noqa: E402
from gcm_pipeline.robot.model import Robot  # noqa: E402

TOL_P, TOL_R = 1e-4, 1e-3


def pinocchio_fk(robot: Robot, q: np.ndarray) -> np.ndarray:
    data = robot.model.createData()
    out = np.empty((len(q), 4, 4))
    for i, qi in enumerate(q):
        pin.forwardKinematics(robot.model, data, qi)
        pin.updateFramePlacements(robot.model, data)
        out[i] = data.oMf[robot.grasp_frame_id].homogeneous
    return out


def shell_targets(
    robot: Robot, n: int, lo: float, hi: float, rng: np.random.Generator, inward: bool = False
) -> np.ndarray:
    """Poses at ``lo``-``hi`` [m] from the shoulder; random orientations, or with
    the approach axis (z) pointing back at the shoulder (``inward``)."""
    d = rng.normal(size=(n, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    out = np.tile(np.eye(4), (n, 1, 1))
    if inward:
        x = np.cross(-d, rng.normal(size=(n, 3)))
        x /= np.linalg.norm(x, axis=1, keepdims=True)
        out[:, :3, 0], out[:, :3, 1], out[:, :3, 2] = x, np.cross(-d, x), -d
    else:
        out[:, :3, :3] = Rotation.random(n, random_state=rng).as_matrix()
    out[:, :3, 3] = robot.shoulder + rng.uniform(lo, hi, size=(n, 1)) * d
    return out


def independent_ok(robot: Robot, q: np.ndarray, targets: np.ndarray) -> np.ndarray:
    """Re-check solutions without any project code: Pinocchio FK, log3, model limits."""
    model = robot.model
    data = model.createData()
    ok = np.zeros(len(q), dtype=bool)
    for i, (qi, t) in enumerate(zip(q, targets, strict=True)):
        if not np.all(np.isfinite(qi)):
            continue
        pin.forwardKinematics(model, data, qi)
        pin.updateFramePlacements(model, data)
        m = data.oMf[robot.grasp_frame_id]
        pe = np.linalg.norm(m.translation - t[:3, 3])
        re = np.linalg.norm(pin.log3(t[:3, :3].T @ m.rotation))
        inside = np.all(qi > model.lowerPositionLimit) and np.all(qi < model.upperPositionLimit)
        ok[i] = pe <= TOL_P and re <= TOL_R and inside
    return ok


def tracik_rate(robot: Robot, targets: np.ndarray, repeats: int) -> tuple[float, float] | None:
    """TRAC-IK (``pytracik``, the ``bench`` extra) on the same targets: median targets/s
    (one thread, home seed, 5 ms timeout, Speed mode) and its success rate; None if
    pytracik is not installed."""
    try:
        import pytracik
    except ImportError:
        return None
    from gcm_pipeline.geometry.dualquat import quat_from_rotation

    urdf = robot.urdf_path.read_text()
    solver = pytracik.TRAC_IK(
        "panda_link0", robot.grasp_frame, urdf, 0.005, 1e-5, pytracik.SolveType.Speed
    )
    pytracik.set_joint_limits(solver, robot.lower.tolist(), robot.upper.tolist())
    quats = quat_from_rotation(targets[:, :3, :3]).tolist()
    seed = np.asarray(robot.home, dtype=float)
    rates, ok = [], 0
    for _ in range(repeats):
        ok = 0
        t0 = time.perf_counter()
        for t, (w, x, y, z) in zip(targets, quats, strict=True):
            ok += pytracik.ik(solver, seed, t[0, 3], t[1, 3], t[2, 3], x, y, z, w)[0] >= 0
        rates.append(len(targets) / (time.perf_counter() - t0))
    return float(np.median(rates)), ok / len(targets)


def timed(fn: Any, repeats: int) -> tuple[Any, float, float]:
    """Result of the first call, median wall time [s], median CPU time [s]."""
    walls, cpus, result = [], [], None
    for _ in range(repeats):
        w, c = time.perf_counter(), time.process_time()
        out = fn()
        walls.append(time.perf_counter() - w)
        cpus.append(time.process_time() - c)
        if result is None:
            result = out
    return result, float(np.median(walls)), float(np.median(cpus))


def bench_backend(
    robot: Robot,
    backend: str,
    sets: dict[str, np.ndarray],
    repeats: int,
    workers: int,
) -> dict[str, Any]:
    out: dict[str, Any] = {"backend": backend}
    reach = sets["reachable"]
    solve_ik(robot, reach[:4], backend)  # warm-up: seed library / MuJoCo model
    res, wall, cpu = timed(lambda: solve_ik(robot, reach, backend), repeats)
    out["n_reachable"] = len(reach)
    out["recall"] = float(res.success.mean())
    verified = independent_ok(robot, res.q[res.success], reach[res.success])
    fp = int(np.count_nonzero(~verified))
    out["reasons_reachable"] = {
        str(k): int(v) for k, v in zip(*np.unique(res.reason, return_counts=True), strict=True)
    }
    out["rate_1proc"] = len(reach) / wall
    out["rate_1proc_cpu"] = len(reach) / cpu
    out["wall_1proc_s"] = wall
    res_w, wall_w, _ = timed(lambda: solve_ik(robot, reach, backend, workers=workers), repeats)
    out["workers"] = workers
    out["rate_all_cores"] = len(reach) / wall_w
    fp += int(
        np.count_nonzero(~independent_ok(robot, res_w.q[res_w.success], reach[res_w.success]))
    )
    out["recall_all_cores"] = float(res_w.success.mean())
    for name in ("unreachable", "unreachable_near"):
        tg = sets[name]
        r, wall_u, _ = timed(lambda tg=tg: solve_ik(robot, tg, backend), max(1, repeats // 2))
        fp += int(np.count_nonzero(r.success))
        out[f"n_{name}"] = len(tg)
        out[f"successes_{name}"] = int(np.count_nonzero(r.success))
        out[f"rate_{name}"] = len(tg) / wall_u
        out[f"reasons_{name}"] = {
            str(k): int(v) for k, v in zip(*np.unique(r.reason, return_counts=True), strict=True)
        }
    out["false_positives"] = fp
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--robot", default="panda")
    parser.add_argument("--reachable", type=int, default=2000)
    parser.add_argument("--unreachable", type=int, default=500)
    parser.add_argument("--mink-targets", type=int, default=200)
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", default=str(ROOT / "benchmarks" / "results" / "ik.json"))
    args = parser.parse_args()

    load_start = os.getloadavg()
    t_start = time.time()
    robot = load_robot(args.robot)
    rng = np.random.default_rng(args.seed)
    q = robot.random_configurations(args.reachable, rng)
    sets = {
        "reachable": pinocchio_fk(robot, q),
        "unreachable": shell_targets(robot, args.unreachable, 1.3, 2.0, rng),
        "unreachable_near": shell_targets(robot, args.unreachable, 0.75, 0.94, rng, inward=True),
    }
    workers = os.cpu_count() or 1
    results = [bench_backend(robot, "pinocchio", sets, args.repeats, workers)]
    m = args.mink_targets
    mink_sets = {k: v[:m] if k == "reachable" else v[: max(1, m // 4)] for k, v in sets.items()}
    results.append(bench_backend(robot, "mink", mink_sets, max(1, args.repeats // 3), workers))
    tracik = tracik_rate(robot, sets["reachable"], max(1, args.repeats // 2))
    ratio = results[0]["rate_1proc"] / results[1]["rate_1proc"]
    ratio_all = results[0]["rate_all_cores"] / results[1]["rate_all_cores"]

    # manipulability of 100,000 configurations (Jacobians included)
    qm = robot.random_configurations(100_000, rng)
    _, manip_wall, _ = timed(lambda: yoshikawa(robot.jacobian(qm)), args.repeats)
    _, all_wall, _ = timed(lambda: manipulability_metrics(robot, qm), max(1, args.repeats // 2))

    load_end = os.getloadavg()
    header = (
        f"{'backend':<10} {'targets':>8} {'recall':>8} {'FP':>4} {'1 proc/s':>10} "
        f"{'(cpu)/s':>9} {'all cores/s':>12}"
    )
    print(f"robot {robot.name}, {workers} cores, repeats {args.repeats} (medians)")
    print(header)
    print("-" * len(header))
    for r in results:
        print(
            f"{r['backend']:<10} {r['n_reachable']:>8} {100 * r['recall']:>7.2f}% "
            f"{r['false_positives']:>4} {r['rate_1proc']:>10.0f} {r['rate_1proc_cpu']:>9.0f} "
            f"{r['rate_all_cores']:>12.0f}"
        )
    print(f"speed ratio pinocchio / mink: {ratio:.0f}x (1 process), {ratio_all:.0f}x (all cores)")
    if tracik is not None:
        print(
            f"TRAC-IK (same targets, one thread): {tracik[0]:.0f} targets/s, success "
            f"{100 * tracik[1]:.1f} %; pinocchio / TRAC-IK: "
            f"{results[0]['rate_1proc'] / tracik[0]:.1f}x (1 process), "
            f"{results[0]['rate_all_cores'] / tracik[0]:.1f}x (all cores)"
        )
    else:
        print("TRAC-IK: not installed (pip install '.[bench]')")
    print(
        f"unreachable sets: pinocchio {results[0]['rate_unreachable']:.0f}/s (pre-filter), "
        f"{results[0]['rate_unreachable_near']:.0f}/s (inside max_reach: "
        f"{results[0]['reasons_unreachable_near']})"
    )
    print(
        f"manipulability of 100,000 configurations: {manip_wall:.3f} s (Yoshikawa incl. "
        f"Jacobians), {all_wall:.3f} s (all 4 metrics)"
    )
    print(f"load average at start {load_start[0]:.2f}, at end {load_end[0]:.2f}")

    report = {
        "robot": robot.name,
        "position_tolerance_m": TOL_P,
        "orientation_tolerance_rad": TOL_R,
        "cores": workers,
        "repeats": args.repeats,
        "seed": args.seed,
        "mink_subset": {k: len(v) for k, v in mink_sets.items()},
        "backends": results,
        "speed_ratio_pinocchio_over_mink_1proc": ratio,
        "speed_ratio_pinocchio_over_mink_all_cores": ratio_all,
        "tracik_targets_per_s": None if tracik is None else tracik[0],
        "tracik_success": None if tracik is None else tracik[1],
        "ratio_over_tracik_1proc": None if tracik is None else results[0]["rate_1proc"] / tracik[0],
        "ratio_over_tracik_all_cores": None
        if tracik is None
        else results[0]["rate_all_cores"] / tracik[0],
        "manipulability_100k_s": manip_wall,
        "manipulability_all_metrics_100k_s": all_wall,
        "load_average_start": load_start,
        "load_average_end": load_end,
        "duration_s": time.time() - t_start,
        "date_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
        "versions": {
            "python": platform.python_version(),
            "numpy": np.__version__,
            "pinocchio": pin.__version__,
        },
        "note": "Shared machine: timings are medians of repeats; mink on a subset.",
    }
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(report, indent=2) + "\n")
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
