"""Manifold query benchmark: batched ``locate`` on ~100,000-pose manifolds.

Run from the repository root::

    python benchmarks/bench_manifold.py            # writes results/manifold.json
    python benchmarks/bench_manifold.py --quick    # small sizes, prints only

Two manifolds of about 100,000 densified poses (the table a run writes):

* ``many_triangles``: the bottle config with 2,000 side grasps (3,981 triangles)
  densified with ``subdivisions: 7``;
* ``bottle_dense``: the bottle example (126 triangles) with ``subdivisions: 40``.

Queries are points of the manifold (random triangle, Dirichlet weights) moved
by a random twist: ``near`` 1 cm / 3 deg standard deviation per axis, ``far``
5 cm / 15 deg. Figures are medians of repeats (the machine is shared):
queries per second of ``GraspManifold.locate`` (wall clock, and per second of
this process's CPU time, which other jobs on the machine disturb less), and in the same run the
reference a user had before, the nearest densified row by a KD-tree over the
rows in the same pose metric, with how much nearer the continuous answer is.
Correctness on the same queries: brute force over a 30-subdivided lattice of
every triangle (``locate`` must never be farther). Target: >= 10,000 queries/s.
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
from scipy.spatial import cKDTree

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import gcm_pipeline as gcm
from gcm_pipeline.geometry.dualquat import dq_exp, dq_mul
from gcm_pipeline.geometry.pose_metric import pose_features
from gcm_pipeline.manifold.locate import _cells
from gcm_pipeline.manifold.surface import blend
from gcm_pipeline.pipeline import grasp_manifold

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "benchmarks" / "results" / "manifold.json"

SETUPS = {
    "many_triangles": [
        "candidates.count=2000",
        "manifold.max_edge_length=0.03",
        "densify.subdivisions=7",
    ],
    "bottle_dense": ["densify.subdivisions=40"],
}
NOISE = {"near": (0.01, np.deg2rad(3.0)), "far": (0.05, np.deg2rad(15.0))}


def median_time(fn: Callable[[], Any], repeats: int) -> tuple[float, float]:
    """Median wall time and median CPU time (this process) [s] of ``fn``."""
    wall, cpu = [], []
    for _ in range(repeats):
        t0, c0 = time.perf_counter(), time.process_time()
        fn()
        wall.append(time.perf_counter() - t0)
        cpu.append(time.process_time() - c0)
    return statistics.median(wall), statistics.median(cpu)


def _tree(dq: np.ndarray) -> cKDTree:
    feat = pose_features(dq)
    flip = feat.copy()
    flip[:, 3:] *= -1
    return cKDTree(np.concatenate((feat, flip)))


def bench(name: str, overrides: list[str], n_queries: int, repeats: int) -> dict[str, Any]:
    cfg = gcm.load_config(ROOT / "configs" / "bottle_side.yaml", overrides)
    cand = gcm.generate_candidates(cfg)
    mesh = gcm.build_manifold(cand, cfg)
    table = gcm.densify(cand, mesh, cfg)
    t0 = time.perf_counter()
    manifold = grasp_manifold(mesh, table, cfg)
    _ = manifold.locator
    build = time.perf_counter() - t0
    rng = np.random.default_rng(0)
    rows_tree = _tree(np.asarray(table["dq"]))
    out: dict[str, Any] = {
        "poses": len(table),
        "candidates": len(cand),
        "triangles": len(mesh.triangles),
        "locator_build_s": build,
        "locator": repr(manifold.locator),
    }
    corners = manifold.poses[manifold.triangles]
    lat = _cells(30)[1].reshape(-1, 3)
    for label, (pos, ang) in NOISE.items():
        tri = rng.integers(0, len(mesh.triangles), n_queries)
        on = manifold.sample(tri, rng.dirichlet((1, 1, 1), n_queries))
        twist = np.concatenate(
            (rng.normal(size=(n_queries, 3)) * ang, rng.normal(size=(n_queries, 3)) * pos), axis=1
        )
        queries = dq_mul(on, dq_exp(twist))
        t_loc, c_loc = median_time(lambda q=queries: manifold.locate(q), repeats)
        t_row, c_row = median_time(lambda q=queries: rows_tree.query(pose_features(q)), repeats)
        loc = manifold.locate(queries)
        d_row, _ = rows_tree.query(pose_features(queries))
        # brute force on a subset (every point of a 30-subdivided lattice of each
        # triangle near the query's own triangle would do; all triangles is exact)
        sub = rng.choice(n_queries, size=min(300, n_queries), replace=False)
        best = np.full(len(sub), np.inf)
        for a in range(0, len(corners), 256):
            t = np.arange(a, min(a + 256, len(corners)))
            pts = blend(np.repeat(corners[t], len(lat), axis=0), np.tile(lat, (len(t), 1)))
            d, _ = _tree(pts).query(pose_features(queries[sub]))
            best = np.minimum(best, d)
        gap = best - loc.distance[sub]
        out[label] = {
            "queries": n_queries,
            "noise_position_m": pos,
            "noise_angle_deg": float(np.rad2deg(ang)),
            "locate_queries_per_s": n_queries / t_loc,
            "locate_queries_per_cpu_s": n_queries / c_loc,
            "nearest_row_queries_per_s": n_queries / t_row,
            "nearest_row_queries_per_cpu_s": n_queries / c_row,
            "median_distance_m": float(np.median(loc.distance)),
            "median_nearest_row_distance_m": float(np.median(d_row)),
            "median_gain_over_nearest_row_m": float(np.median(d_row - loc.distance)),
            "brute_force_subset": len(sub),
            "locate_never_farther_than_brute_force": bool(np.all(gap >= -1e-12)),
            "max_brute_force_minus_locate_m": float(gap.max()),
        }
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--quick", action="store_true", help="small sizes, no JSON")
    parser.add_argument("--repeats", type=int, default=5)
    args = parser.parse_args()
    n = 2000 if args.quick else 10000
    result: dict[str, Any] = {
        "benchmark": "manifold",
        "date": datetime.now(timezone.utc).isoformat(timespec="seconds"),
        "machine": {"platform": platform.platform(), "cpus": os.cpu_count()},
        "command": "python benchmarks/bench_manifold.py" + (" --quick" if args.quick else ""),
        "target_locate_queries_per_s": 10000,
    }
    for name, overrides in SETUPS.items():
        r = bench(name, overrides, n, 3 if args.quick else args.repeats)
        result[name] = r
        size = f"{r['poses']:,} poses, {r['triangles']:,} triangles"
        print(f"{name}: {size}, locator built in {r['locator_build_s']:.2f} s")
        for label in NOISE:
            x = r[label]
            noise = f"{x['noise_position_m'] * 100:.0f} cm, {x['noise_angle_deg']:.0f} deg"
            d_loc = x["median_distance_m"] * 1000
            d_row = x["median_nearest_row_distance_m"] * 1000
            print(
                f"  {label:4s} ({noise}): locate {x['locate_queries_per_s']:,.0f} queries/s "
                f"({x['locate_queries_per_cpu_s']:,.0f} per CPU s), "
                f"nearest row {x['nearest_row_queries_per_s']:,.0f}/s; median distance "
                f"{d_loc:.2f} mm vs row {d_row:.2f} mm; vs brute force: never farther "
                f"{x['locate_never_farther_than_brute_force']}, at most "
                f"{x['max_brute_force_minus_locate_m'] * 1000:.3f} mm nearer"
            )
    if not args.quick:
        RESULTS.parent.mkdir(parents=True, exist_ok=True)
        RESULTS.write_text(json.dumps(result, indent=2) + "\n", encoding="utf-8")
        print(f"wrote {RESULTS}")


if __name__ == "__main__":
    main()
