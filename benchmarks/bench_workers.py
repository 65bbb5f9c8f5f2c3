#!/usr/bin/env python
"""``workers: auto`` against one worker on the reachability stage: idle, one core hogged, both.

Work: the dense bottle of ``bench_pipeline.py`` (``configs/bottle_side.yaml``
with 80 side grasps and ``subdivisions: 28``, about 56,000 poses, approach on,
table and bottle in the collision world). Each run builds a fresh engine
(:func:`gcm_pipeline.pipeline.reachability_engine`) and times
:func:`gcm_pipeline.check_reachability` end to end, so the worker pool's
start-up is charged to the run that forks it.

Four scenarios, in one run: **idle** (whatever else the machine runs),
**hog_core_0** (a busy loop pinned to core 0 by ``taskset``),
**hog_all_cores** (one pinned busy loop per core) and **hog_core_0_late**
(the loop on core 0 starts 1.5 s into each run, after auto has read an
idle machine and decided: the load auto cannot see); the loops are child
processes of this benchmark, killed after their scenario or run. A scenario is
``--pairs`` (9) pairs of runs, ``auto`` and ``1`` back to back, the order
alternating from pair to pair (auto, one; one, auto; ...) so that neither
setting always runs first. The machine is shared (single runs of one setting
differ by up to 3.5x here), so the figure is the **median of the per-pair
ratios** auto/one (the target: at least 1), with their spread (quartiles,
least and most). Per auto run the benchmark records how many workers auto
chose and the idle cores it read: where it chose 1, auto ran the one-worker
code on this process (the same chunks; the first cut in two where it solved a
quarter chunk to read the cores longer), so that pair's ratio shows what the
probe costs and the machine's noise
(``ratio_where_auto_chose_one``; the
pairs where it forked: ``ratio_where_auto_forked``). Also recorded: the load
average (``os.getloadavg``) before every pair and at the end, and whether
every run gave the same reachable flags, and per run the CPU the rest of the
machine used meanwhile (``others_cores_*``, in cores: the hogs and other jobs),
so that a pair whose two runs met different loads can be told apart.

Run from the repository root: ``python benchmarks/bench_workers.py``
(about ten minutes on 2 cores, more under load); writes ``benchmarks/results/workers.json``.
``--scenarios hog_core_0,hog_all_cores --pairs 25`` runs a subset with more pairs (to resolve
a ratio near 1) and writes ``workers_<names>.json`` beside it.
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
from gcm_pipeline.reach.engine import available_cores  # noqa: E402

CONFIG = ROOT / "configs" / "bottle_side.yaml"
DENSE = ["candidates.count=80", "densify.subdivisions=28"]
RESULTS = ROOT / "benchmarks" / "results"
#: Scenario name -> (cores with a busy loop all along, cores with one from LATE_S), of the cores.
SCENARIOS: dict[str, Any] = {
    "idle": lambda cores: ([], []),
    "hog_core_0": lambda cores: (cores[:1], []),
    "hog_all_cores": lambda cores: (cores, []),
    "hog_core_0_late": lambda cores: ([], cores[:1]),
}
#: When the late hogs start, into a run [s]: after auto's probe (a quarter chunk, about 0.1 s).
LATE_S = 1.5


def hogs(cores: list[int]) -> list[subprocess.Popen[bytes]]:
    """One busy loop per core in ``cores``, pinned there with ``taskset``."""
    loop = [sys.executable, "-c", "while True: pass"]
    procs = [subprocess.Popen(["taskset", "-c", str(c), *loop]) for c in cores]
    time.sleep(1.0)  # let them show up in the kernel's counters
    return procs


def late_hog(core: int, delay: float) -> subprocess.Popen[bytes]:
    """A busy loop that starts on ``core`` ``delay`` seconds from now."""
    loop = f"import time; time.sleep({delay})\nwhile True: pass"
    return subprocess.Popen(["taskset", "-c", str(core), sys.executable, "-c", loop])


def cpu_now() -> tuple[float, float, float]:
    """The machine's busy CPU time, this process's and its reaped children's [s], the clock."""
    with open("/proc/stat", encoding="ascii") as f:
        ticks = [float(x) for x in f.readline().split()[1:9]]  # the "cpu" line: every core
    busy = (sum(ticks) - ticks[3] - ticks[4]) / os.sysconf("SC_CLK_TCK")  # not idle, iowait
    t = os.times()
    return busy, t.user + t.system + t.children_user + t.children_system, time.perf_counter()


def one_run(grasps: Any, workers: str, late: list[int] | None = None) -> dict[str, Any]:
    """The stage on ``grasps`` with ``ik.workers=workers``: its rate and the workers used.

    ``late``: cores that a busy loop takes ``LATE_S`` into the run (after auto decided).
    ``others_cores``: the CPU the rest of the machine used meanwhile (the hogs, other
    jobs) [cores]: the machine's busy time less the stage's (this process and its
    workers, reaped by ``engine.close``), over the wall time.
    """
    cfg = load_config(CONFIG, [*DENSE, f"ik.workers={workers}"])
    robot = P.robot_from_config(cfg)
    engine = P.reachability_engine(robot, cfg)
    procs = []
    try:
        procs = [late_hog(c, LATE_S) for c in late or []]
        start = cpu_now()
        t0 = time.perf_counter()
        done = P.check_reachability(grasps, robot, cfg, engine=engine)
        wall = time.perf_counter() - t0
    finally:
        engine.close()
        end = cpu_now()  # before the late hogs are reaped: their time is the others'
        for p in procs:
            p.kill()
            p.wait()
    others = ((end[0] - start[0]) - (end[1] - start[1])) / (end[2] - start[2])
    return {
        "wall_s": wall,
        "poses_per_s": len(done) / wall,
        "workers_used": int(engine.workers_used),
        "idle_seen": engine.idle_seen,
        "others_cores": others,
        "reachable": np.asarray(done["reachable"]).copy(),
    }


def spread(x: list[float]) -> dict[str, float]:
    """Median, quartiles, least and most of ``x``."""
    q = np.percentile(x, [0, 25, 50, 75, 100])
    return dict(
        zip(("min", "q1", "median", "q3", "max"), (round(float(v), 3) for v in q), strict=True)
    )


def scenario(
    grasps: Any, pairs: int, hog_cores: list[int], late: list[int] | None = None
) -> dict[str, Any]:
    """``pairs`` pairs of an auto and a one-worker run, alternating, under hogs on ``hog_cores``.

    ``late``: cores whose busy loop starts during each run (see :func:`one_run`).
    """
    procs = hogs(hog_cores)
    rows, flags = [], []
    try:
        for i in range(pairs):
            load = os.getloadavg()[0]
            order = ("auto", "1") if i % 2 == 0 else ("1", "auto")
            got = {s: one_run(grasps, s, late) for s in order}
            flags += [got["auto"].pop("reachable"), got["1"].pop("reachable")]
            rows.append(
                {
                    "first": order[0],
                    "load_1min": round(load, 2),
                    "auto_poses_per_s": round(got["auto"]["poses_per_s"]),
                    "one_poses_per_s": round(got["1"]["poses_per_s"]),
                    "ratio": round(got["auto"]["poses_per_s"] / got["1"]["poses_per_s"], 3),
                    "auto_workers": got["auto"]["workers_used"],
                    "auto_idle_cores_seen": None
                    if got["auto"]["idle_seen"] is None
                    else round(got["auto"]["idle_seen"], 2),
                    "others_cores_auto_run": round(got["auto"]["others_cores"], 2),
                    "others_cores_one_run": round(got["1"]["others_cores"], 2),
                }
            )
            print(f"  pair {i + 1}: {rows[-1]}", flush=True)
    finally:
        for p in procs:
            p.kill()
            p.wait()
    ratios = [r["ratio"] for r in rows]
    forked = [r["ratio"] for r in rows if r["auto_workers"] > 1]
    same = [r["ratio"] for r in rows if r["auto_workers"] == 1]
    return {
        "hog_cores": hog_cores,
        "late_hog_cores": late or [],
        "ratio_auto_over_one": spread(ratios),
        "ratio_where_auto_forked": spread(forked) if forked else None,
        "ratio_where_auto_chose_one": spread(same) if same else None,
        "one_poses_per_s": spread([r["one_poses_per_s"] for r in rows]),
        "auto_poses_per_s": spread([r["auto_poses_per_s"] for r in rows]),
        "identical_reachable": all(np.array_equal(f, flags[0]) for f in flags),
        # pair by pair, in order (one list per column)
        "pairs": {key: [r[key] for r in rows] for key in rows[0]},
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--pairs", type=int, default=9, help="auto/one pairs per scenario")
    parser.add_argument(
        "--scenarios",
        default=",".join(SCENARIOS),
        help=f"comma-separated subset of {', '.join(SCENARIOS)} (default: all)",
    )
    parser.add_argument(
        "--out",
        help="JSON file (default: benchmarks/results/workers.json for every scenario, "
        "workers_<names>.json for a subset)",
    )
    args = parser.parse_args()
    if args.pairs < 1:
        sys.exit("bench_workers: --pairs must be at least 1")
    names = [s.strip() for s in args.scenarios.split(",") if s.strip()]
    unknown = [s for s in names if s not in SCENARIOS]
    if unknown or not names:
        sys.exit(f"bench_workers: --scenarios: unknown {unknown}; choose from {list(SCENARIOS)}")
    every = set(names) == set(SCENARIOS)
    out = (
        Path(args.out)
        if args.out
        else RESULTS / ("workers.json" if every else f"workers_{'_'.join(names)}.json")
    )
    if shutil.which("taskset") is None:
        sys.exit("bench_workers: the hog scenarios need taskset (util-linux)")

    t_start = time.time()
    cfg = load_config(CONFIG, DENSE)
    candidates = P.generate_candidates(cfg)
    grasps = P.densify(candidates, P.build_manifold(candidates, cfg), cfg)
    one_run(grasps, "1")  # warm-up: caches, compiled kernels
    cores = sorted(os.sched_getaffinity(0))
    report: dict[str, Any] = {
        "work": "bottle_side, 80 side grasps, subdivisions 28, approach 10 cm, table + bottle",
        "poses": len(grasps),
        "command": "python benchmarks/bench_workers.py"
        + (f" --pairs {args.pairs}" if args.pairs != 9 else "")
        + ("" if every else f" --scenarios {','.join(names)}"),
        "load_average_start": [round(x, 2) for x in os.getloadavg()],
    }
    for name in names:
        hog_cores, late = SCENARIOS[name](cores)
        when = f", from {LATE_S} s into each run on cores {late}" if late else ""
        print(f"{name}: hogs on cores {hog_cores}{when}", flush=True)
        report[name] = scenario(grasps, args.pairs, hog_cores, late)
        r, chose = report[name]["ratio_auto_over_one"], report[name]["pairs"]["auto_workers"]
        print(
            f"{name}: auto/one median {r['median']:.3f} (quartiles {r['q1']:.3f}-{r['q3']:.3f}, "
            f"range {r['min']:.3f}-{r['max']:.3f}), auto chose {chose}",
            flush=True,
        )
    report.update(
        load_average_end=[round(x, 2) for x in os.getloadavg()],
        duration_s=round(time.time() - t_start),
        date_utc=time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
        cores=available_cores(),
        versions={"python": platform.python_version(), "numpy": np.__version__},
    )
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(report, indent=2) + "\n")
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
