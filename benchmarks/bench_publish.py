"""Benchmark: build and write the self-contained HTML scene for 1,000 and 100,000 grasps.

Run from the repository root::

    python benchmarks/bench_publish.py [--repeats 3]

Times :func:`gcm_pipeline.outputs.html.write_scene_html` (robot meshes,
object, table, batched grasp glyphs, manifold, top-k animation, camera, page
written to disk) on synthetic grasp tables shaped like the pipeline's, and the
start of a live viewer (loopback meshcat server + 1,000 grasps). Prints a
table and writes ``benchmarks/results/publish.json``. Target: < 3 s for
100,000 grasps.
"""

from __future__ import annotations

import argparse
import json
import platform
import statistics
import sys
import tempfile
import time
from pathlib import Path
from types import SimpleNamespace

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from gcm_pipeline.config import Config  # noqa: E402
from gcm_pipeline.config.robot_spec import load_robot  # noqa: E402
from gcm_pipeline.geometry.dualquat import dq_from_matrix  # noqa: E402
from gcm_pipeline.outputs import html, live  # noqa: E402
from gcm_pipeline.pipeline.outputs import publish_options, scene_options  # noqa: E402
from gcm_pipeline.table import GraspTable  # noqa: E402

RESULTS = ROOT / "benchmarks" / "results" / "publish.json"
SIZES = (1_000, 100_000)
TARGET_S = 3.0


def config() -> Config:
    return Config.from_dict(
        {
            "object": {
                "shape": "cylinder",
                "dims": {"radius": 0.035, "height": 0.22},
                "pose": {"xyz": [0.5, 0.0, 0.0]},
            },
            "candidates": {"source": "cylinder_side", "count": 36},
            "ranking": {"top_k": 10},
            "publish": {"html": True, "plots": False},
        }
    )


def grasp_table(robot, n: int, seed: int = 0) -> tuple[GraspTable, SimpleNamespace]:
    """Side grasps around the cylinder (70 % reachable with FK-consistent-looking q)."""
    rng = np.random.default_rng(seed)
    theta = rng.uniform(-np.pi, np.pi, n)
    h = rng.uniform(0.04, 0.18, n)
    c, s = np.cos(theta), np.sin(theta)
    m = np.zeros((n, 4, 4))
    m[:, 3, 3] = 1.0
    m[:, :3, 0] = [0.0, 0.0, 1.0]  # x = cylinder axis
    m[:, :3, 1] = np.c_[-s, c, np.zeros(n)]  # y = tangent
    m[:, :3, 2] = np.c_[-c, -s, np.zeros(n)]  # z = towards the axis
    m[:, :3, 3] = np.c_[0.5 + 0.025 * c, 0.025 * s, h]
    reach = rng.random(n) < 0.7
    q = np.full((n, robot.nq), np.nan)
    q[reach] = robot.home + rng.normal(0.0, 0.2, (int(reach.sum()), robot.nq))
    manip = np.where(reach, rng.uniform(0.01, 0.12, n), np.nan)
    rank = np.zeros(n, dtype=np.int64)
    idx = np.flatnonzero(reach)
    rank[idx[np.argsort(-manip[idx])]] = np.arange(1, len(idx) + 1)
    nc = 36
    grasps = GraspTable(
        {
            "dq": dq_from_matrix(m),
            "origin": np.where(np.arange(n) < nc, "candidate", "interpolated"),
            "reachable": reach,
            "reason": np.where(reach, "", "no_ik"),
            "q": q,
            "manipulability": manip,
            "rank": rank,
        }
    )
    tris = np.array([[i, (i + 1) % nc, (i + 6) % nc] for i in range(nc)])
    manifold = SimpleNamespace(chart=rng.uniform(size=(nc, 2)), triangles=tris, projection="pca")
    return grasps, manifold


def bench_html(robot, n: int, repeats: int) -> dict:
    grasps, manifold = grasp_table(robot, n)
    options = scene_options(config())
    runs = []
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "scene.html"
        for _ in range(repeats):
            t0 = time.perf_counter()
            info = html.write_scene_html(path, grasps, manifold, robot, options)
            runs.append(time.perf_counter() - t0)
        size = path.stat().st_size
    return {
        "grasps": n,
        "median_s": statistics.median(runs),
        "runs_s": runs,
        "html_mb": size / 1e6,
        "glyph": info.glyph,
        "meshcat_objects": info.meshcat_objects,
    }


def bench_live(robot, n: int, repeats: int) -> dict:
    grasps, manifold = grasp_table(robot, n)
    options = publish_options(
        Config.from_dict({**config().to_dict(), "publish": {"meshcat": True}})
    )
    runs = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        viewer = live.open_viewer(grasps, manifold, robot, options)
        runs.append(time.perf_counter() - t0)
        viewer.close()
    return {"grasps": n, "median_s": statistics.median(runs), "runs_s": runs}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args()
    robot = load_robot("panda")
    html = [bench_html(robot, n, args.repeats) for n in SIZES]
    live = bench_live(robot, 1_000, args.repeats)
    print(f"{'grasps':>8} {'median [s]':>11} {'runs [s]':>24} {'html [MB]':>10} glyph")
    for r in html:
        runs = " ".join(f"{t:.2f}" for t in r["runs_s"])
        print(
            f"{r['grasps']:>8} {r['median_s']:>11.3f} {runs:>24} {r['html_mb']:>10.1f} {r['glyph']}"
        )
    print(
        f"live viewer (loopback server start + {live['grasps']} grasps): {live['median_s']:.3f} s"
    )
    big = html[-1]
    ok = big["median_s"] < TARGET_S
    print(f"target < {TARGET_S:g} s for {big['grasps']:,} grasps: {'met' if ok else 'MISSED'}")
    RESULTS.parent.mkdir(parents=True, exist_ok=True)
    RESULTS.write_text(
        json.dumps(
            {
                "benchmark": "publish: build and write scene.html",
                "command": "python benchmarks/bench_publish.py",
                "repeats": args.repeats,
                "target_s": TARGET_S,
                "target_met": ok,
                "html": html,
                "live_viewer": live,
                "machine": {
                    "python": platform.python_version(),
                    "processor": platform.processor() or platform.machine(),
                },
            },
            indent=2,
        )
        + "\n",
        encoding="utf-8",
    )
    print(f"wrote {RESULTS}")


if __name__ == "__main__":
    main()
