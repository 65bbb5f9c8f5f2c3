"""Query guarantee on a real grasp set: every reachable row, isolated or not, is found.

Run from the repository root::

    python benchmarks/bench_query_guarantee.py              # writes results/query_guarantee.json
    python benchmarks/bench_query_guarantee.py --quick      # 300 candidates, prints only
    python benchmarks/bench_query_guarantee.py --structure families   # the default structure

The set: ACRONYM's mug (``Mug_*.h5``, its 1,290 successful grasps) with the mug's
mesh (``meshes/Mug/*.obj``) scaled by the file's ``object/scale`` and stood on
the table (its lowest point at z = 0) 0.5 m in front of the Panda; the run's
config is the one of ``configs/from_file.yaml`` for an ACRONYM file
(cylindrical chart, ``max_edge_length`` 0.08 m, ``max_edge_angle_deg`` 50,
``densify.subdivisions`` 2). Most of its candidates are in no kept triangle.

Targets (issue 30):

* ``nearest_reachable`` at every reachable row's exact pose returns that pose
  (distance <= 1e-6 m) with a verified solution: Pinocchio FK of the returned
  ``q`` reproduces the pose within the run's IK tolerances;
* at a pose 5 mm (pose metric) off every reachable row, in a random direction
  of SE(3), the answer is never farther than the nearest reachable row;
* ``locate`` >= 10,000 queries/s: in the same run, medians of alternating
  repeats of the locator before this change (``--before``, a git revision:
  triangles only) and now (triangles and isolated candidates), on 10,000
  queries as in ``bench_manifold.py`` (``near``: 1 cm / 3 deg, ``far``: 5 cm /
  15 deg per axis), on the mug's manifold and on ``bench_manifold``'s
  ``many_triangles`` bottle (3,981 triangles).
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import os
import platform
import statistics
import subprocess
import sys
import tempfile
import time
from datetime import datetime, timezone
from pathlib import Path
from types import ModuleType
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import gcm_pipeline as gcm
from gcm_pipeline.geometry.dualquat import dq_exp, dq_mul, dq_to_matrix
from gcm_pipeline.geometry.pose_metric import pose_distance
from gcm_pipeline.pipeline import grasp_manifold

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "benchmarks" / "results" / "query_guarantee.json"
DATA = Path("/work/data/acronym/data/examples")
NOISE = {"near": (0.01, np.deg2rad(3.0)), "far": (0.05, np.deg2rad(15.0))}


MANIFOLDS = {
    "chart": "{projection: cylindrical, max_edge_length: 0.08, max_edge_angle_deg: 50}",
    "families": "{structure: families}",  # the bounds it derives from the data
}


def mug_config(data: Path, out: Path, limit: int | None, structure: str = "chart") -> Path:
    """Write the run's config for ACRONYM's mug (mesh and scale as its file names them)."""
    import h5py
    import trimesh

    (h5,) = sorted((data / "grasps").glob("Mug_*.h5"))
    with h5py.File(h5, "r") as fh:
        mesh_file = data / fh["object/file"][()].decode()
        scale = float(fh["object/scale"][()])
    lowest = float(trimesh.load(mesh_file, force="mesh").bounds[0, 2]) * scale
    limit_line = f"  limit: {limit}\n" if limit else ""
    path = out / "mug.yaml"
    path.write_text(
        f"""seed: 0
robot: {{spec: panda}}
object:
  shape: mesh
  mesh: {mesh_file}
  scale: {scale!r}
  pose: {{xyz: [0.5, 0.0, {-lowest!r}], rpy_deg: [0, 0, 0]}}
candidates:
  source: file
  path: {h5}
  format: acronym
  frame: object
  success_only: true
{limit_line}manifold: {MANIFOLDS[structure]}
densify: {{subdivisions: 2, method: dlb}}
environment: {{table: {{height: 0.0}}}}
publish: {{html: false, plots: false}}
"""
    )
    return path


def off_by(dq: np.ndarray, rng: np.random.Generator, dist: float) -> np.ndarray:
    """Poses exactly ``dist`` [m] (pose metric) from ``dq``, in random directions."""
    twist = rng.normal(size=(len(dq), 6))
    twist[:, :3] *= 0.5
    for _ in range(3):  # the metric is not linear in the twist's angle: rescale
        twist *= (dist / pose_distance(dq_mul(dq, dq_exp(twist)), dq))[:, None]
    return dq_mul(dq, dq_exp(twist))


def fk_error(run: gcm.RunResult, dq: np.ndarray, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Position [m] and angle [rad] between Pinocchio FK of ``q`` and the poses ``dq``."""
    target = np.linalg.inv(run.config.robot.base_pose.matrix()) @ dq_to_matrix(dq)
    reached = run.robot.fk_pinocchio(q)
    pos = np.linalg.norm(reached[:, :3, 3] - target[:, :3, 3], axis=1)
    rel = np.einsum("nji,njk->nik", target[:, :3, :3], reached[:, :3, :3])
    angle = np.arccos(np.clip((np.trace(rel, axis1=1, axis2=2) - 1) / 2, -1, 1))
    return pos, angle


def guarantee(run: gcm.RunResult, m: gcm.GraspManifold, seed: int) -> dict[str, Any]:
    """The two nearest_reachable targets over every reachable row."""
    g = m.grasps
    dq = np.asarray(g["dq"])
    reach = np.asarray(g["reachable"], dtype=bool)
    rows = np.flatnonzero(reach)
    isolated = np.isin(rows, m.mesh.unused)
    tol_p, tol_a = run.config.ik.position_tolerance, run.config.ik.orientation_tolerance
    t0 = time.perf_counter()
    at = m.nearest_reachable(dq[rows])
    t_at = time.perf_counter() - t0
    pos, ang = fk_error(run, np.nan_to_num(at.dq), np.nan_to_num(at.q))
    verified = at.found & (pos < tol_p) & (ang < tol_a)
    exact = at.found & (at.distance <= 1e-6)
    rng = np.random.default_rng(seed)
    queries = off_by(dq[rows], rng, 0.005)
    t0 = time.perf_counter()
    off = m.nearest_reachable(queries)
    t_off = time.perf_counter() - t0
    nearest_row = np.full(len(rows), np.inf)
    for a in range(0, len(rows), 256):  # (256, R) distances at a time
        sl = slice(a, a + 256)
        nearest_row[sl] = pose_distance(dq[rows][None], queries[sl, None]).min(axis=1)
    excess = np.where(off.found, off.distance - nearest_row, np.inf)
    pos_o, ang_o = fk_error(run, np.nan_to_num(off.dq), np.nan_to_num(off.q))
    return {
        "reachable_rows": len(rows),
        "isolated_reachable_rows": int(isolated.sum()),
        "at_row": {
            "exact_within_1e-6_m": int(exact.sum()),
            "exact_isolated": int((exact & isolated).sum()),
            "max_distance_m": float(np.max(at.distance)),
            "fk_verified": int(verified.sum()),
            "max_fk_position_error_m": float(pos.max()),
            "max_fk_angle_error_rad": float(ang.max()),
            "answered_by_the_isolated_row": int((at.vertex[isolated] == rows[isolated]).sum()),
            "queries_per_s": len(rows) / t_at,
        },
        "off_5mm": {
            "query_distance_to_own_row_m": [
                float(pose_distance(queries, dq[rows]).min()),
                float(pose_distance(queries, dq[rows]).max()),
            ],
            "found": int(off.found.sum()),
            "never_farther_than_nearest_reachable_row": int((excess <= 1e-12).sum()),
            "max_excess_m": float(excess.max()),
            "median_distance_m": float(np.median(off.distance)),
            "median_nearest_row_m": float(np.median(nearest_row)),
            "fk_verified": int((off.found & (pos_o < tol_p) & (ang_o < tol_a)).sum()),
            "answers_at_isolated_rows": int((off.vertex >= 0).sum()),
            "queries_per_s": len(rows) / t_off,
        },
    }


def locator_before(ref: str) -> ModuleType | None:
    """The locate module at git revision ``ref`` (None if git or the revision is missing)."""
    try:
        text = subprocess.run(
            ["git", "show", f"{ref}:gcm_pipeline/manifold/locate.py"],
            cwd=ROOT,
            capture_output=True,
            text=True,
            check=True,
        ).stdout
    except (OSError, subprocess.CalledProcessError):
        return None
    path = Path(tempfile.mkdtemp()) / "locate_before.py"
    path.write_text(text)
    spec = importlib.util.spec_from_file_location("locate_before", path)
    assert spec is not None and spec.loader is not None
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def speed(m: gcm.GraspManifold, before: ModuleType | None, n: int, repeats: int) -> dict[str, Any]:
    """Queries/s of locate now and before, alternating repeats; medians."""
    rng = np.random.default_rng(0)
    now = m.locator
    old = None
    if before is not None and len(m):
        old = before.TriangleLocator(m.poses[m.triangles], method=m.method)
    out: dict[str, Any] = {
        "triangles": len(m),
        "isolated_points": len(now.points),
        "locator": repr(now),
    }
    base = np.asarray(m.grasps["dq"])
    for label, (pos, ang) in NOISE.items():
        start = base[rng.integers(0, len(base), n)]
        twist = np.c_[rng.normal(size=(n, 3)) * ang, rng.normal(size=(n, 3)) * pos]
        q = dq_mul(start, dq_exp(twist))
        t_now, t_old = [], []
        for _ in range(repeats):
            t0 = time.perf_counter()
            now.locate(q)
            t_now.append(time.perf_counter() - t0)
            if old is not None:
                t0 = time.perf_counter()
                old.locate(q)
                t_old.append(time.perf_counter() - t0)
        got = now.locate(q)
        row: dict[str, Any] = {
            "queries": n,
            "locate_queries_per_s": n / statistics.median(t_now),
            "answers_at_isolated_points": int((got.vertex >= 0).sum()),
        }
        if old is not None:
            ref = old.locate(q)
            to_pts = np.full(n, np.inf)  # brute force over the isolated points
            for a in range(0, len(now.points) and n, 500):
                d = pose_distance(now.points[None], q[a : a + 500, None])
                to_pts[a : a + 500] = d.min(axis=1)
            row.update(
                before_queries_per_s=n / statistics.median(t_old),
                equals_min_of_before_and_points=bool(
                    np.all(np.abs(got.distance - np.minimum(ref.distance, to_pts)) <= 1e-12)
                ),
                nearer_than_before=int((got.distance < ref.distance - 1e-12).sum()),
                median_gain_over_before_m=float(np.median(ref.distance - got.distance)),
            )
        out[label] = row
    return out


def many_triangles() -> gcm.GraspManifold:
    """``bench_manifold``'s ``many_triangles`` bottle (candidates and manifold only)."""
    over = ["candidates.count=2000", "manifold.max_edge_length=0.03", "densify.subdivisions=7"]
    cfg = gcm.load_config(ROOT / "configs" / "bottle_side.yaml", over)
    cand = gcm.generate_candidates(cfg)
    mesh = gcm.build_manifold(cand, cfg)
    return grasp_manifold(mesh, gcm.densify(cand, mesh, cfg), cfg)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--data", type=Path, default=DATA, help="ACRONYM's data/examples folder")
    parser.add_argument("--quick", action="store_true", help="300 candidates, no JSON")
    parser.add_argument("--before", default="b4a6eca", help="git revision of the old locator")
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument(
        "--structure",
        choices=sorted(MANIFOLDS),
        default="chart",
        help="the manifold's structure (families: results/query_guarantee_families.json)",
    )
    args = parser.parse_args()
    limit = 300 if args.quick else None
    n = 2000 if args.quick else 10000
    with tempfile.TemporaryDirectory() as tmp:
        cfg = gcm.load_config(mug_config(args.data, Path(tmp), limit, args.structure))
        t0 = time.perf_counter()
        run = gcm.Pipeline(cfg).run(out_dir=Path(tmp) / "run", progress=False)
        run_s = time.perf_counter() - t0
        assert run.run_dir is not None
        m = gcm.load_manifold(run.run_dir)
        g = guarantee(run, m, seed=30)
        before = locator_before(args.before)
        speeds = {"mug": speed(m, before, n, args.repeats)}
        if not args.quick:
            speeds["many_triangles"] = speed(many_triangles(), before, n, args.repeats)
    result: dict[str, Any] = {
        "benchmark": "query_guarantee",
        "date": datetime.now(timezone.utc).isoformat(timespec="seconds"),
        "machine": {"platform": platform.platform(), "cpus": os.cpu_count()},
        "command": "python benchmarks/bench_query_guarantee.py"
        + (" --quick" if args.quick else ""),
        "set": {
            "grasps": str(sorted((args.data / "grasps").glob("Mug_*.h5"))[0].name),
            "candidates": m.mesh.n_vertices,
            "triangles": len(m),
            "isolated_candidates": len(m.mesh.unused),
            "rows": len(m.grasps),
            "run_s": run_s,
        },
        "targets": {
            "at_row_distance_m": 1e-6,
            "off_distance_m": 0.005,
            "locate_queries_per_s": 10000,
        },
        "guarantee": g,
        "locate_speed": speeds,
        "locate_before": args.before if before is not None else None,
    }
    s, a, o = result["set"], g["at_row"], g["off_5mm"]
    print(
        f"mug: {s['candidates']} candidates, {s['triangles']} triangles, "
        f"{s['isolated_candidates']} isolated; {g['reachable_rows']} reachable rows "
        f"({g['isolated_reachable_rows']} isolated)"
    )
    print(
        f"  at each reachable row: {a['exact_within_1e-6_m']} of {g['reachable_rows']} exact "
        f"(max {a['max_distance_m']:.1e} m), {a['fk_verified']} FK-verified "
        f"(max {a['max_fk_position_error_m']:.1e} m, {a['max_fk_angle_error_rad']:.1e} rad)"
    )
    print(
        f"  5 mm off each: {o['never_farther_than_nearest_reachable_row']} of "
        f"{g['reachable_rows']} never farther than the nearest reachable row "
        f"(max excess {o['max_excess_m']:.1e} m), {o['fk_verified']} FK-verified"
    )
    for name, sp in speeds.items():
        for label in NOISE:
            x = sp[label]
            was = (
                f", before {x['before_queries_per_s']:,.0f}/s (equal to min(before, points): "
                f"{x['equals_min_of_before_and_points']})"
                if "before_queries_per_s" in x
                else ""
            )
            print(
                f"  locate {name} {label} ({sp['triangles']} triangles, {sp['isolated_points']} "
                f"points): {x['locate_queries_per_s']:,.0f} queries/s{was}"
            )
    if not args.quick:
        out = RESULTS
        if args.structure != "chart":
            out = RESULTS.with_name(f"query_guarantee_{args.structure}.json")
        result["structure"] = args.structure
        out.parent.mkdir(parents=True, exist_ok=True)
        out.write_text(json.dumps(result, indent=2) + "\n", encoding="utf-8")
        print(f"wrote {out}")


if __name__ == "__main__":
    main()
