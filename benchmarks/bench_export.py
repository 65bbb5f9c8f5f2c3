"""Benchmark: size and write time of every ``gcm export`` format for the bottle run.

Run from the repository root::

    python benchmarks/bench_export.py [--repeats 3]

Runs ``configs/bottle_side.yaml`` (no HTML, no plots) into a temporary
directory, then exports it in each format with
:func:`gcm_pipeline.pipeline.outputs.export_run` (in this process, after one
warm-up export that imports rosbags and loads the robot) and records the
median time, the file's size, and for the ROS 2 bag the serialised bytes of
each topic. Prints a table and writes ``benchmarks/results/export.json``.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import sys
import tempfile
import time
from datetime import datetime, timezone
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from gcm_pipeline.config import load_config  # noqa: E402
from gcm_pipeline.pipeline import Pipeline  # noqa: E402
from gcm_pipeline.pipeline.outputs import export_run  # noqa: E402

RESULTS = ROOT / "benchmarks" / "results" / "export.json"
CONFIG = ROOT / "configs" / "bottle_side.yaml"
#: (label, format, trajectory)
CASES = (
    ("mcap", "mcap", False),
    ("moveit", "moveit", False),
    ("moveit_trajectory", "moveit", True),
    ("parquet", "parquet", False),
    ("npz", "npz", False),
)


def topic_bytes(path: Path) -> dict[str, int]:
    """Serialised bytes of each topic of a bag (rosbags' reader)."""
    from rosbags.rosbag2 import Reader

    sizes: dict[str, int] = {}
    with Reader(path) as reader:
        for conn, _, raw in reader.messages():
            sizes[conn.topic] = sizes.get(conn.topic, 0) + len(raw)
    return sizes


def bench(run: Path, out_dir: Path, repeats: int) -> list[dict]:
    results = []
    for label, fmt, trajectory in CASES:
        out = out_dir / f"grasps_{label}.{fmt}"
        runs = []
        for _ in range(repeats):
            start = time.perf_counter()
            written = export_run(run, fmt, out=out, trajectory=trajectory)
            runs.append(time.perf_counter() - start)
        item = {
            "format": label,
            "grasps": written.rows,
            "median_s": statistics.median(runs),
            "runs_s": runs,
            "bytes": out.stat().st_size,
        }
        if fmt == "mcap":
            item["topic_bytes"] = topic_bytes(out)
        results.append(item)
    return results


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        run = Path(tmp) / "run"
        cfg = load_config(CONFIG, ("publish.html=false", "publish.plots=false"))
        Pipeline(cfg).run(run, progress=False)
        export_run(run, "mcap", out=Path(tmp) / "warm.mcap")  # imports, robot, typestore
        with (run / "grasps.csv").open() as fh:
            rows = sum(1 for _ in fh) - 1
        results = bench(run, Path(tmp), args.repeats)
    print(f"bottle run: {rows} grasps, {results[0]['grasps']} reachable")
    print(f"{'format':>18} {'grasps':>7} {'median [s]':>11} {'size [KB]':>10}")
    for r in results:
        print(
            f"{r['format']:>18} {r['grasps']:>7} {r['median_s']:>11.3f} {r['bytes'] / 1e3:>10.1f}"
        )
    RESULTS.parent.mkdir(parents=True, exist_ok=True)
    RESULTS.write_text(
        json.dumps(
            {
                "benchmark": "export: size and write time of each gcm export format",
                "command": "python benchmarks/bench_export.py",
                "date": datetime.now(timezone.utc).isoformat(timespec="seconds"),
                "load_average": [round(x, 2) for x in os.getloadavg()],
                "config": "configs/bottle_side.yaml",
                "run_grasps": rows,
                "repeats": args.repeats,
                "exports": results,
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
