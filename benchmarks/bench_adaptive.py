"""Adaptive densification benchmark: the bottle example against uniform lattices.

Run from the repository root::

    python benchmarks/bench_adaptive.py            # writes results/adaptive.json
    python benchmarks/bench_adaptive.py --quick    # level 3 only, prints only

For each level L: the bottle example (``configs/bottle_side.yaml``: IK,
collisions with table and bottle, approach check, ranked by ``combined``)
densified adaptively with ``densify.adaptive: {max_level: L}`` (and with
``refine: [boundary]`` only), and uniformly with ``subdivisions: 2**L``, each
checked exactly as ``gcm run`` does. The adaptive result is interpolated at
every row of the uniform lattice (barycentric interpolation of
reachability inside the faces of the adaptive rows, reachable when >= 0.5)
and compared with the uniform lattice's own classification.

Reported: rows checked (= IK solves: every row is one IK target) of both,
their ratio, the agreement, and wall times of the reachability stage. Target
(issue 14): >= 99 % agreement with >= 5x fewer IK solves.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time
from datetime import datetime, timezone
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import gcm_pipeline as gcm
from gcm_pipeline.manifold.lattice import interpolate, row_mesh
from gcm_pipeline.pipeline import ReachabilityCheck, densify_adaptive

ROOT = Path(__file__).resolve().parents[1]
CONFIG = ROOT / "configs" / "bottle_side.yaml"
RESULTS = ROOT / "benchmarks" / "results" / "adaptive.json"


def agreement(adaptive: gcm.GraspTable, uniform: gcm.GraspTable, mesh: Any, n_c: int) -> float:
    rows = row_mesh(adaptive, mesh.triangles, n_c)
    inner = np.asarray(uniform["origin"]) == "interpolated"
    predicted = np.zeros(len(uniform), dtype=bool)
    predicted[~inner] = np.asarray(adaptive["reachable"])[:n_c]
    value = interpolate(
        rows,
        np.asarray(adaptive["reachable"], dtype=float),
        uniform["triangle"][inner],
        uniform["weights"][inner],
    )
    predicted[inner] = value >= 0.5
    return float(np.mean(predicted == np.asarray(uniform["reachable"])))


def run_level(level: int, robot: gcm.Robot) -> dict[str, Any]:
    ucfg = gcm.load_config(CONFIG, [f"densify.subdivisions={2**level}"])
    cand = gcm.generate_candidates(ucfg)
    mesh = gcm.build_manifold(cand, ucfg)
    t0 = time.perf_counter()
    uniform = gcm.check_reachability(gcm.densify(cand, mesh, ucfg), robot, ucfg)
    t_uniform = time.perf_counter() - t0
    out: dict[str, Any] = {
        "level": level,
        "uniform_subdivisions": 2**level,
        "uniform_ik_solves": len(uniform),
        "uniform_reachable": int(np.count_nonzero(uniform["reachable"])),
        "uniform_reachability_s": t_uniform,
    }
    for name, refine in (("boundary_metric", "[boundary, metric]"), ("boundary", "[boundary]")):
        cfg = gcm.load_config(
            CONFIG, [f"densify.adaptive={{max_level: {level}, refine: {refine}}}"]
        )
        check = ReachabilityCheck(robot, cfg)
        t0 = time.perf_counter()
        adaptive = densify_adaptive(cand, mesh, robot, cfg, check=check)
        t_adaptive = time.perf_counter() - t0
        assert check.solved == len(adaptive)
        out[name] = {
            "refine": refine,
            "ik_solves": check.solved,
            "fewer_ik_solves": len(uniform) / check.solved,
            "agreement": agreement(adaptive, uniform, mesh, len(cand)),
            "reachability_s": t_adaptive,
            "rows_by_level": {
                str(k): int(v)
                for k, v in zip(*np.unique(adaptive["level"], return_counts=True), strict=True)
            },
        }
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--quick", action="store_true", help="level 3 only, no JSON")
    parser.add_argument("--levels", type=int, nargs="*", default=None)
    args = parser.parse_args()
    levels = args.levels or ([3] if args.quick else [3, 4, 5])
    robot = gcm.load_robot("panda")
    result: dict[str, Any] = {
        "benchmark": "adaptive",
        "date": datetime.now(timezone.utc).isoformat(timespec="seconds"),
        "machine": {"platform": platform.platform(), "cpus": os.cpu_count()},
        "command": "python benchmarks/bench_adaptive.py" + (" --quick" if args.quick else ""),
        "config": "configs/bottle_side.yaml",
        "target": {"agreement": 0.99, "fewer_ik_solves": 5.0},
        "levels": [],
    }
    for level in levels:
        r = run_level(level, robot)
        result["levels"].append(r)
        print(
            f"L = {level}: uniform subdivisions {2**level}: {r['uniform_ik_solves']:,} IK solves, "
            f"{r['uniform_reachability_s']:.1f} s"
        )
        for name in ("boundary_metric", "boundary"):
            x = r[name]
            print(
                f"  adaptive refine {x['refine']}: {x['ik_solves']:,} IK solves "
                f"({x['fewer_ik_solves']:.1f}x fewer), agreement {100 * x['agreement']:.2f} %, "
                f"{x['reachability_s']:.1f} s"
            )
    if not args.quick:
        RESULTS.parent.mkdir(parents=True, exist_ok=True)
        RESULTS.write_text(json.dumps(result, indent=2) + "\n", encoding="utf-8")
        print(f"wrote {RESULTS}")


if __name__ == "__main__":
    main()
