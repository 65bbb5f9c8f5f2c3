"""Benchmark: reading a big run back (``gcm show``, ``gcm query``, ``read_run``, a quoted CSV).

Run from the repository root::

    python benchmarks/bench_read.py --run DIR [--before CHECKOUT] [--repeats 3]

``DIR`` is a run directory; without it the benchmark makes the million-row
run first (``gcm run configs/bottle_side.yaml --set candidates.count=80
--set densify.subdivisions=120``, a few minutes) in a temporary directory.
Each case runs as a fresh process of ``python -m gcm_pipeline`` (or a
one-line ``python -c``) and is measured by its CPU time (user + system, from
the child's resource usage) and its wall time. With ``--before CHECKOUT`` (a
checkout of the code before) every case also runs on that code, the two
alternating, and the figures hold both, their CPU ratio and whether the two
printed the same bytes. The quoted case reads a copy of the run's
``grasps.csv`` with one more text column whose cells hold commas, quotes and
newlines (written by ``write_grasps_csv``). Prints a table and writes
``benchmarks/results/read.json``.
"""

from __future__ import annotations

import argparse
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

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "benchmarks" / "results" / "read.json"
BIG_RUN = ["--set", "candidates.count=80", "--set", "densify.subdivisions=120"]
POSE = ["0.5", "-0.05", "0.12", "0.5", "-0.5", "-0.5", "-0.5"]
POSES = [
    *("--pose", *POSE),
    *("--pose", "0.45", "0.05", "0.2", "0.7071067811865476", "0", "0.7071067811865476", "0"),
    *("--pose", "2", "2", "2", "1", "0", "0", "0"),
]
READ_CSV = (
    "from gcm_pipeline.rundir.grasps_csv import read_grasps_csv as r; import sys; r(sys.argv[1])"
)
READ_RUN = "from gcm_pipeline.rundir.run import read_run; import sys; read_run(sys.argv[1])"
MAKE_QUOTED = """
import sys
import numpy as np
from gcm_pipeline.rundir.grasps_csv import read_grasps_csv, write_grasps_csv
g = read_grasps_csv(sys.argv[1])
words = np.array(["plain", "a, b", 'say "hi"', "two\\nlines", "", 'x,"y"\\nz'])
write_grasps_csv(g.with_columns(label=words[np.arange(len(g)) % len(words)]), sys.argv[2])
"""


def cases(run: Path, quoted: Path) -> dict[str, list[str]]:
    """The measured commands (arguments after ``python``)."""
    gcm = ["-m", "gcm_pipeline"]
    return {
        "show": [*gcm, "show", str(run)],
        "query_one_pose": [*gcm, "query", str(run), "--pose", *POSE],
        "query_three_poses_json": [*gcm, "query", str(run), *POSES, "--json"],
        "read_run": ["-c", READ_RUN, str(run)],
        "read_quoted_csv": ["-c", READ_CSV, str(quoted)],
    }


def measure_child(tree: Path, args: list[str]) -> tuple[float, float, bytes]:
    """CPU [s] (user + system), wall [s] and stdout of one fresh process on ``tree``'s code.

    The CPU time is the change of this process's children's resource usage.
    """
    import resource

    env = {**os.environ, "PYTHONPATH": str(tree)}
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    start = time.perf_counter()
    done = subprocess.run(
        [sys.executable, *args], capture_output=True, env=env, check=False, cwd=tree
    )
    wall = time.perf_counter() - start
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    if done.returncode:
        raise RuntimeError(f"{args} failed on {tree}: {done.stderr.decode()[-500:]}")
    cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    return cpu, wall, done.stdout


def bench(run: Path, quoted: Path, trees: dict[str, Path], repeats: int) -> dict:
    results: dict = {}
    for tree in trees.values():  # Numba's kernel cache of each checkout, imports
        measure_child(tree, cases(run, quoted)["query_one_pose"])
    for name, args in cases(run, quoted).items():
        runs: dict[str, list[tuple[float, float, bytes]]] = {label: [] for label in trees}
        for _ in range(repeats):
            for label, tree in trees.items():  # alternating
                runs[label].append(measure_child(tree, args))
        item: dict = {}
        for label, got in runs.items():
            item[label] = {
                "cpu_s_median": round(statistics.median(r[0] for r in got), 3),
                "wall_s_median": round(statistics.median(r[1] for r in got), 3),
                "cpu_s": [round(r[0], 3) for r in got],
            }
        if "before" in runs:
            item["cpu_ratio_before_over_after"] = round(
                item["before"]["cpu_s_median"] / item["after"]["cpu_s_median"], 2
            )
            outs = {r[2] for got in runs.values() for r in got}
            item["identical_stdout"] = len(outs) == 1
        results[name] = item
        print(name, json.dumps(item))
    return results


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--run", type=Path, help="a run directory (default: make the big run)")
    parser.add_argument("--before", type=Path, help="a checkout of the code before")
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args()
    trees = {"after": ROOT}
    if args.before:
        trees["before"] = args.before.resolve()
    load_before = [round(x, 2) for x in os.getloadavg()]
    with tempfile.TemporaryDirectory() as tmp:
        run = args.run
        if run is None:
            run = Path(tmp) / "run"
            config = str(ROOT / "configs" / "bottle_side.yaml")
            subprocess.run(
                [sys.executable, "-m", "gcm_pipeline", "run", config, *BIG_RUN, "--out", str(run)]
                + ["-q"],
                check=True,
                env={**os.environ, "PYTHONPATH": str(ROOT)},
            )
        quoted = Path(tmp) / "quoted.csv"
        subprocess.run(
            [sys.executable, "-c", MAKE_QUOTED, str(run / "grasps.csv"), str(quoted)],
            check=True,
            env={**os.environ, "PYTHONPATH": str(ROOT)},
        )
        with (run / "grasps.csv").open("rb") as fh:
            rows = sum(1 for _ in fh) - 1
        results = bench(run, quoted, trees, args.repeats)
    RESULTS.parent.mkdir(parents=True, exist_ok=True)
    command = "python benchmarks/bench_read.py" + (" --before CHECKOUT" if args.before else "")
    RESULTS.write_text(
        json.dumps(
            {
                "benchmark": "read: gcm show, gcm query, read_run, a quoted grasps.csv; a big run",
                "command": command,
                "date": datetime.now(timezone.utc).isoformat(timespec="seconds"),
                "load_before": load_before,
                "load_after": [round(x, 2) for x in os.getloadavg()],
                "run": "configs/bottle_side.yaml " + " ".join(BIG_RUN),
                "run_rows": rows,
                "repeats": args.repeats,
                "cases": results,
                "machine": {
                    "python": platform.python_version(),
                    "platform": platform.platform(),
                    "cpus": os.cpu_count(),
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
