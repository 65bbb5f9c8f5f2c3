"""Benchmark: placement-study throughput on Ray with 1 and 2 workers, and Ray's overhead.

Study: the paper's bottle (``configs/bottle_side.yaml``: 72 side grasps, 1,044
poses after densification, table, approach check) moved over a 5 x 5 grid of
the table at two yaw angles: 50 placements (``--placements 10`` for a quick
run: a 5 x 1 x 2 grid). Publishing and ``best/`` are off: only the placements
are timed.

* ``inline``: the placements one after the other in this process, on one
  :class:`~gcm_pipeline.study.worker.PlacementWorker` (the reference);
* ``ray_1``, ``ray_2``: ``gcm study`` on Ray started on this machine with 1 and
  2 workers (actors).

Figures: placements/s of the placement phase (from the first placement sent
to the last result written; start-up, i.e. starting Ray and building each
worker's robot, seed library and collision geometry, is reported apart),
the speed-up of 2 workers over 1 (target >= 1.7 on 2 cores) and Ray's overhead
with 1 worker against inline (target <= 10 %). Correctness on the same work:
every placement's reachable count must be identical in the three runs.

Every process uses one BLAS thread (``OMP_NUM_THREADS=1``, as Ray gives its
1-CPU actors), so inline and Ray run the same work.

Run: ``python benchmarks/bench_study.py`` (about 4 minutes on a quiet 2-core
machine; ``--placements 10`` for a quick check; writes
``benchmarks/results/study.json``).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import shutil
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))  # run from a clone, no install
# Ray's workers are new processes: they find the package the same way
os.environ["PYTHONPATH"] = os.pathsep.join(
    [str(ROOT), *filter(None, [os.environ.get("PYTHONPATH")])]
)
os.environ["RAY_USAGE_STATS_ENABLED"] = "0"
# One BLAS thread per process, in this process as in Ray's 1-CPU actors (Ray sets
# OMP_NUM_THREADS=1 for them): the inline reference then does the same work; with
# BLAS's default two threads a placement ran about 2x slower here under load.
for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

from gcm_pipeline.study import Study  # noqa: E402

BOTTLE = ROOT / "configs" / "bottle_side.yaml"


def study_for(placements: int) -> Study:
    """50 placements: x 5 x y 5 x yaw 2; 10: x 5 x yaw 2 (y = 0)."""
    if placements == 50:
        pose = {
            "x": {"from": 0.35, "to": 0.65, "steps": 5},
            "y": {"from": -0.25, "to": 0.25, "steps": 5},
        }
    elif placements == 10:
        pose = {"x": {"from": 0.35, "to": 0.65, "steps": 5}}
    else:
        raise SystemExit("--placements must be 50 or 10")
    return Study.from_dict(
        {
            "base": str(BOTTLE),
            "set": ["publish.html=false", "publish.plots=false"],
            "sweep": {"object_pose": {**pose, "yaw_deg": [0, 20]}},
        }
    )


def run(study: Study, engine: str, workers: int | None, tmp: Path) -> dict:
    out = tmp / f"{engine}_{workers}"
    t0 = time.perf_counter()
    result = study.run(out, engine=engine, workers=workers, progress=False, best_run=False)
    wall = time.perf_counter() - t0
    s = result.summary
    phase = s["timings_s"]["placements"]
    return {
        "engine": engine,
        "workers": s["engine"]["workers"],
        "placements": len(result.rows),
        "failed": len(result.failed),
        "startup_s": s["timings_s"]["startup"],
        "placements_s": phase,
        "placements_per_s": len(result.rows) / phase,
        "wall_s": wall,
        "reachable": [r["reachable"] for r in result.rows],
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--placements", type=int, default=50, choices=(50, 10))
    parser.add_argument("--out", type=Path, default=ROOT / "benchmarks" / "results" / "study.json")
    args = parser.parse_args()
    study = study_for(args.placements)
    tmp = Path(tempfile.mkdtemp(prefix="bench-study-"))
    os.environ.setdefault("RAY_TMPDIR", tempfile.mkdtemp(prefix="ray-", dir="/tmp"))
    try:
        runs = {}
        for name, engine, workers in (
            ("inline", "inline", None),
            ("ray_1", "ray", 1),
            ("ray_2", "ray", 2),
        ):
            r = runs[name] = run(study, engine, workers, tmp)
            print(
                f"{name:7s} {r['placements']} placements in {r['placements_s']:7.2f} s "
                f"= {r['placements_per_s']:.3f} placements/s (start-up {r['startup_s']:.1f} s, "
                f"wall {r['wall_s']:.1f} s, failed {r['failed']})",
                flush=True,
            )
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    speedup = runs["ray_2"]["placements_per_s"] / runs["ray_1"]["placements_per_s"]
    overhead = runs["ray_1"]["placements_s"] / runs["inline"]["placements_s"] - 1.0
    identical = (
        runs["inline"]["reachable"] == runs["ray_1"]["reachable"] == runs["ray_2"]["reachable"]
    )
    print(f"speed-up 2 workers / 1 worker: {speedup:.2f}x (target >= 1.7)")
    print(f"Ray overhead, 1 worker vs inline: {100 * overhead:+.1f} % (target <= 10 %)")
    print(f"identical reachable counts in the three runs: {identical}")
    result = {
        "benchmark": "study",
        "study": f"bottle_side, {args.placements} object placements",
        "runs": {k: {kk: vv for kk, vv in v.items() if kk != "reachable"} for k, v in runs.items()},
        "speedup_2_over_1": speedup,
        "ray_overhead_1_worker": overhead,
        "identical_results": identical,
        "load_average": os.getloadavg(),
        "blas_threads": os.environ.get("OMP_NUM_THREADS"),
        "cpus": os.cpu_count(),
        "python": platform.python_version(),
        "time": time.strftime("%Y-%m-%dT%H:%M:%S"),
    }
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=2) + "\n")
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
