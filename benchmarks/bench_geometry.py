"""Geometry benchmarks: dual quaternion conversions, DLB, triangulation, densify.

Run from the repository root::

    python benchmarks/bench_geometry.py            # full sizes, writes results/geometry.json
    python benchmarks/bench_geometry.py --quick    # small sizes, prints only

Every figure is the median of several repeats (the machine is shared).
Targets (DESIGN.md and issue #2): DLB >= 2,000,000 poses/s, Qhull of
100,000 points < 1 s, Bowyer-Watson of 10,000 points < 5 s.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import sys
import time
from collections.abc import Callable
from datetime import datetime, timezone
from pathlib import Path
from typing import Any

import numpy as np
import scipy

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from gcm_pipeline.geometry.bowyer_watson import bowyer_watson, delaunay
from gcm_pipeline.geometry.dualquat import dq_from_matrix, dq_from_pos_quat, dq_to_matrix
from gcm_pipeline.geometry.pose_blend import dlb
from gcm_pipeline.manifold.build import build_manifold
from gcm_pipeline.manifold.densify import densify
from gcm_pipeline.table import GraspTable

RESULTS = Path(__file__).resolve().parent / "results" / "geometry.json"


def median_time(fn: Callable[[], Any], repeats: int) -> tuple[float, list[float]]:
    """Median wall time [s] of ``fn`` over ``repeats`` runs (after one warm-up for short runs)."""
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return statistics.median(times), times


def random_matrices(rng: np.random.Generator, n: int) -> np.ndarray:
    q = rng.normal(size=(n, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    dq = dq_from_pos_quat(rng.normal(size=(n, 3)), q)
    return dq_to_matrix(dq)


def bench_dualquat(n: int, repeats: int, rng: np.random.Generator) -> dict[str, Any]:
    mats = random_matrices(rng, n)
    t_from, _ = median_time(lambda: dq_from_matrix(mats), repeats)
    t_from_nc, _ = median_time(lambda: dq_from_matrix(mats, check=False), repeats)
    dq = dq_from_matrix(mats)
    t_to, _ = median_time(lambda: dq_to_matrix(dq), repeats)
    weights = rng.dirichlet([1.0, 1.0, 1.0], size=n)
    corners = dq[rng.integers(0, n, size=(n, 3))]
    t_dlb, _ = median_time(lambda: dlb(corners, weights), repeats)
    t_dlb_nc, _ = median_time(lambda: dlb(corners, weights, check=False), repeats)
    shared = dq[:3]
    t_dlb_shared, _ = median_time(lambda: dlb(shared, weights), repeats)
    return {
        "poses": n,
        "matrix_to_dq_poses_per_s": n / t_from,
        "matrix_to_dq_unchecked_poses_per_s": n / t_from_nc,
        "dq_to_matrix_poses_per_s": n / t_to,
        "dlb_poses_per_s": n / t_dlb,
        "dlb_unchecked_poses_per_s": n / t_dlb_nc,
        "dlb_shared_3_poses_per_s": n / t_dlb_shared,
        "notes": "dlb: (N, 3, 8) vertex poses with (N, 3) weights, validated (check=True); "
        "dlb_shared: 3 poses (3, 8) with (N, 3) weights",
    }


def bench_triangulation(
    n_large: int, n_small: int, repeats: int, bw_repeats: int, rng: np.random.Generator
) -> dict[str, Any]:
    large = rng.random((n_large, 2))
    small = rng.random((n_small, 2))
    t_qhull, _ = median_time(lambda: delaunay(large, "qhull"), repeats)
    t_bw_small, _ = median_time(lambda: bowyer_watson(small), bw_repeats)
    t_bw_large, _ = median_time(lambda: bowyer_watson(large), bw_repeats)
    return {
        "qhull_points": n_large,
        "qhull_s": t_qhull,
        "bowyer_watson_points": n_large,
        "bowyer_watson_s": t_bw_large,
        "bowyer_watson_small_points": n_small,
        "bowyer_watson_small_s": t_bw_small,
        "notes": "uniform random points in the unit square; median wall time",
    }


def bench_densify(
    n_candidates: int, subdivisions: int, repeats: int, rng: np.random.Generator
) -> dict[str, Any]:
    pos = np.column_stack((rng.random((n_candidates, 2)), np.zeros(n_candidates)))
    rv = rng.normal(scale=0.1, size=(n_candidates, 4))
    rv[:, 0] = 1.0
    grasps = GraspTable({"dq": dq_from_pos_quat(pos, rv)})
    manifold = build_manifold(grasps)
    out = densify(grasps, manifold, subdivisions=subdivisions)
    t, _ = median_time(lambda: densify(grasps, manifold, subdivisions=subdivisions), repeats)
    t_dib, _ = median_time(
        lambda: densify(grasps, manifold, subdivisions=subdivisions, method="dib"),
        max(1, repeats // 2),
    )
    return {
        "candidates": n_candidates,
        "triangles": int(len(manifold.triangles)),
        "subdivisions": subdivisions,
        "output_poses": int(len(out)),
        "densify_dlb_poses_per_s": len(out) / t,
        "densify_dib_poses_per_s": len(out) / t_dib,
        "notes": "planar candidates, rotations within ~12 deg; whole stage incl. dedupe "
        "and table columns",
    }


def main(argv: list[str] | None = None) -> dict[str, Any]:
    """Run the benchmarks, print a summary and (unless --quick) write the JSON."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="small sizes, do not write JSON")
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--output", type=Path, default=RESULTS)
    args = parser.parse_args(argv)

    rng = np.random.default_rng(0)
    if args.quick:
        sizes = {"poses": 100_000, "large": 10_000, "small": 2_000, "cand": 300, "bw_rep": 1}
    else:
        sizes = {"poses": 1_000_000, "large": 100_000, "small": 10_000, "cand": 2_000, "bw_rep": 3}
    results: dict[str, Any] = {
        "benchmark": "geometry",
        "date_utc": datetime.now(timezone.utc).isoformat(timespec="seconds"),
        "repeats": args.repeats,
        "machine": {
            "cpus": os.cpu_count(),
            "platform": platform.platform(),
            "python": platform.python_version(),
            "numpy": np.__version__,
            "scipy": scipy.__version__,
            "shared": "machine shared with other jobs; figures are medians",
        },
        "command": "python benchmarks/bench_geometry.py",
    }
    results["dualquat"] = bench_dualquat(sizes["poses"], args.repeats, rng)
    results["triangulation"] = bench_triangulation(
        sizes["large"], sizes["small"], args.repeats, sizes["bw_rep"], rng
    )
    results["densify"] = bench_densify(sizes["cand"], 16, args.repeats, rng)
    tri = results["triangulation"]
    results["targets"] = {
        "dlb_ge_2M_poses_per_s": results["dualquat"]["dlb_poses_per_s"] >= 2e6,
        "qhull_100k_lt_1s": tri["qhull_s"] < 1.0 if tri["qhull_points"] >= 100_000 else None,
        "bowyer_watson_10k_lt_5s": (
            tri["bowyer_watson_small_s"] < 5.0
            if tri["bowyer_watson_small_points"] >= 10_000
            else None
        ),
    }

    dq, dn = results["dualquat"], results["densify"]
    print(
        f"matrix -> dq     {dq['matrix_to_dq_poses_per_s'] / 1e6:8.2f} M poses/s ({dq['poses']:,})"
    )
    print(f"dq -> matrix     {dq['dq_to_matrix_poses_per_s'] / 1e6:8.2f} M poses/s")
    print(f"DLB (N,3,8)      {dq['dlb_poses_per_s'] / 1e6:8.2f} M poses/s")
    print(f"DLB shared 3     {dq['dlb_shared_3_poses_per_s'] / 1e6:8.2f} M poses/s")
    print(f"Qhull            {tri['qhull_s']:8.3f} s ({tri['qhull_points']:,} points)")
    small = tri["bowyer_watson_small_points"]
    print(f"Bowyer-Watson    {tri['bowyer_watson_small_s']:8.3f} s ({small:,} points)")
    print(
        f"Bowyer-Watson    {tri['bowyer_watson_s']:8.3f} s ({tri['bowyer_watson_points']:,} points)"
    )
    rate = dn["densify_dlb_poses_per_s"] / 1e6
    print(f"densify DLB      {rate:8.2f} M poses/s ({dn['output_poses']:,} poses)")
    print(f"densify DIB      {dn['densify_dib_poses_per_s'] / 1e6:8.2f} M poses/s")
    print(f"targets          {results['targets']}")
    if not args.quick:
        args.output.parent.mkdir(parents=True, exist_ok=True)
        args.output.write_text(json.dumps(results, indent=2) + "\n")
        print(f"wrote {args.output}")
    return results


if __name__ == "__main__":
    main()
