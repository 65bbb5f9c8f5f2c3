#!/usr/bin/env python
"""The reachability stage on 1 worker, 2 workers and ``workers: auto``, idle and under a CPU hog.

Work: the dense bottle of ``bench_pipeline.py`` (``configs/bottle_side.yaml``
with 80 side grasps and ``subdivisions: 28``, about 56,000 poses, approach on,
table and bottle in the collision world). Each run builds a fresh engine
(:func:`gcm_pipeline.pipeline.reachability_engine`) and times
:func:`gcm_pipeline.check_reachability` end to end, so the worker pool's
start-up is charged to the run that needs it.

Two conditions, in one run: **idle** (whatever else the machine runs) and
**hog**: a busy loop pinned to core 0 (``taskset -c 0``, a child process of
this benchmark, killed after). In each condition the settings are
interleaved (1, 2, auto, 1, 2, auto, ...) so that the machine's load hits
them alike; the figures are medians over ``--repeats`` (5). The ratio that the
issue's target reads is ``auto / one worker`` (at least 1 wanted), per
condition, also paired (each repeat's auto run over the one-worker run of
the same repeat, median of those ratios: slow drifts of the load cancel).
Also recorded: how many workers ``auto`` chose in each run and the load
average before and after.

Run from the repository root: ``python benchmarks/bench_workers.py``
(about three minutes); writes ``benchmarks/results/workers.json``.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import shutil
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))  # run from a clone, no install

from gcm_pipeline import pipeline as P  # noqa: E402
from gcm_pipeline.config import load_config  # noqa: E402

CONFIG = ROOT / "configs" / "bottle_side.yaml"
DENSE = ["candidates.count=80", "densify.subdivisions=28"]
SETTINGS = ("1", "2", "auto")


def hog() -> subprocess.Popen[bytes]:
    """A busy loop on core 0 (pinned with ``taskset`` where it exists)."""
    loop = [sys.executable, "-c", "while True: pass"]
    cmd = ["taskset", "-c", "0", *loop] if shutil.which("taskset") else loop
    proc = subprocess.Popen(cmd)
    time.sleep(1.0)  # let it show up in the kernel's counters
    return proc


def one_run(grasps: Any, workers: str) -> dict[str, Any]:
    """The stage on ``grasps`` with ``ik.workers=workers``: wall time and the workers used."""
    cfg = load_config(CONFIG, [*DENSE, f"ik.workers={workers}"])
    robot = P.robot_from_config(cfg)
    engine = P.reachability_engine(robot, cfg)
    try:
        t0 = time.perf_counter()
        done = P.check_reachability(grasps, robot, cfg, engine=engine)
        wall = time.perf_counter() - t0
    finally:
        engine.close()
    return {
        "wall_s": wall,
        "poses_per_s": len(done) / wall,
        "workers_used": int(getattr(engine, "workers_used", engine.workers)),
        "reachable": np.asarray(done["reachable"]).copy(),
    }


def condition(grasps: Any, repeats: int) -> dict[str, Any]:
    """Every setting ``repeats`` times, interleaved: medians, runs, workers used."""
    runs: dict[str, list[dict[str, Any]]] = {s: [] for s in SETTINGS}
    for _ in range(repeats):
        for s in SETTINGS:
            runs[s].append(one_run(grasps, s))
    first = runs[SETTINGS[0]][0]["reachable"]
    same = all(np.array_equal(r["reachable"], first) for rs in runs.values() for r in rs)
    out: dict[str, Any] = {"identical_reachable": bool(same)}
    for s, rs in runs.items():
        rates = [r["poses_per_s"] for r in rs]
        out[f"workers_{s}"] = {
            "poses_per_s": float(np.median(rates)),
            "runs_poses_per_s": [round(x) for x in rates],
            "workers_used": [r["workers_used"] for r in rs],
        }
    out["ratio_auto_over_one"] = (
        out["workers_auto"]["poses_per_s"] / out["workers_1"]["poses_per_s"]
    )
    out["ratio_two_over_one"] = out["workers_2"]["poses_per_s"] / out["workers_1"]["poses_per_s"]
    # paired: each repeat's auto (or 2) run over that repeat's one-worker run, so that
    # the slow drifts of the machine's load cancel; the median of those ratios
    for s, key in (("auto", "ratio_auto_over_one_paired"), ("2", "ratio_two_over_one_paired")):
        pairs = [
            b["poses_per_s"] / a["poses_per_s"] for a, b in zip(runs["1"], runs[s], strict=True)
        ]
        out[key] = float(np.median(pairs))
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--repeats", type=int, default=5, help="runs per setting (median)")
    parser.add_argument("--no-hog", action="store_true", help="only the idle condition")
    parser.add_argument("--out", default=str(ROOT / "benchmarks" / "results" / "workers.json"))
    args = parser.parse_args()

    t_start = time.time()
    cfg = load_config(CONFIG, DENSE)
    candidates = P.generate_candidates(cfg)
    grasps = P.densify(candidates, P.build_manifold(candidates, cfg), cfg)
    one_run(grasps, "1")  # warm-up: caches, compiled kernels
    report: dict[str, Any] = {
        "work": "bottle_side, 80 side grasps, subdivisions 28, approach 10 cm, table + bottle",
        "poses": len(grasps),
        "command": "python benchmarks/bench_workers.py"
        + (f" --repeats {args.repeats}" if args.repeats != 5 else ""),
        "load_average_start": os.getloadavg(),
    }
    report["idle"] = condition(grasps, max(1, args.repeats))
    if not args.no_hog:
        proc = hog()
        try:
            report["hog_on_core_0"] = condition(grasps, max(1, args.repeats))
        finally:
            proc.kill()
            proc.wait()
    report.update(
        load_average_end=os.getloadavg(),
        duration_s=time.time() - t_start,
        date_utc=time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
        cores=os.cpu_count(),
        versions={"python": platform.python_version(), "numpy": np.__version__},
    )
    for name in ("idle", "hog_on_core_0"):
        if name not in report:
            continue
        c = report[name]
        rates = ", ".join(
            f"{s}: {c[f'workers_{s}']['poses_per_s']:,.0f} "
            f"(used {c[f'workers_{s}']['workers_used']})"
            for s in SETTINGS
        )
        print(f"{name}: poses/s {rates}")
        print(
            f"  auto/one {c['ratio_auto_over_one']:.2f} (paired "
            f"{c['ratio_auto_over_one_paired']:.2f}), two/one {c['ratio_two_over_one']:.2f} "
            f"(paired {c['ratio_two_over_one_paired']:.2f}), "
            f"identical reachable flags: {c['identical_reachable']}"
        )
    print(
        f"load average at start {report['load_average_start'][0]:.2f}, end "
        f"{report['load_average_end'][0]:.2f}"
    )
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(report, indent=2, default=str) + "\n")
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
