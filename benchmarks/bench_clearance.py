"""Benchmark: the clearance per configuration, compiled kernels against the NumPy code.

Run from the repository root::

    python benchmarks/bench_clearance.py [--repeats 7]

Collects the configurations whose clearance the reachability stage computes (its
reachable rows: the dense bottle for the Panda, ``configs/bottle_side.yaml`` with 80
candidates and subdivisions 28; ``configs/bottle_side_ur5.yaml`` for the UR5 with its
2F-85), plus 20,000 random configurations of each robot, then times
``CollisionChecker.clearance`` on them with the compiled kernels and with the NumPy
code (the reference, as with ``GCM_JIT=0``) in the same process, alternating, and records the
median time per configuration of each, their ratio, and the largest difference of
the two results. Writes ``benchmarks/results/clearance.json``.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import platform
import statistics
import sys
import time
from datetime import datetime, timezone
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from gcm_pipeline import pipeline as P  # noqa: E402
from gcm_pipeline.config import load_config  # noqa: E402
from gcm_pipeline.robot import kernels  # noqa: E402
from gcm_pipeline.robot.collision.clearance import ClearanceQueries  # noqa: E402

RESULTS = ROOT / "benchmarks" / "results" / "clearance.json"
ROBOTS = {
    "panda": ("configs/bottle_side.yaml", ["candidates.count=80", "densify.subdivisions=28"]),
    "ur5": ("configs/bottle_side_ur5.yaml", []),
}


def stage_rows(cfg: Any) -> tuple[Any, np.ndarray]:
    """The stage's checker and the configurations it asks the clearance of (one process)."""
    asked: list[np.ndarray] = []
    real = ClearanceQueries.clearance

    def spy(self: Any, q: Any, precision: float = 1e-3) -> np.ndarray:
        asked.append(np.array(q, dtype=float).reshape(-1, self.robot.nq))
        return real(self, q, precision)

    ClearanceQueries.clearance = spy  # type: ignore[method-assign]
    try:
        candidates = P.generate_candidates(cfg)
        grasps = P.densify(candidates, P.build_manifold(candidates, cfg), cfg)
        robot = P.robot_from_config(cfg)
        with P.reachability_engine(robot, cfg) as engine:
            P.check_reachability(grasps, robot, cfg, engine=engine)
            checker = engine.checker
    finally:
        ClearanceQueries.clearance = real  # type: ignore[method-assign]
    return checker, np.concatenate(asked)


def timed(checker: Any, q: np.ndarray, repeats: int) -> dict[str, Any]:
    """Median seconds per configuration, compiled and NumPy, alternating; their results' gap."""
    times: dict[str, list[float]] = {"compiled": [], "numpy": []}
    out: dict[str, np.ndarray] = {}
    for name in ("compiled", "numpy") * (repeats + 1):  # the first round warms up
        with kernels.suppressed() if name == "numpy" else contextlib.nullcontext():
            t0 = time.perf_counter()
            out[name] = checker.clearance(q)
            times[name].append(time.perf_counter() - t0)
    us = {k: statistics.median(v[1:]) / len(q) * 1e6 for k, v in times.items()}
    gap = np.abs(out["compiled"] - out["numpy"])
    return {
        "configurations": len(q),
        "compiled_us_per_configuration": round(us["compiled"], 3),
        "numpy_us_per_configuration": round(us["numpy"], 3),
        "speedup": round(us["numpy"] / us["compiled"], 2),
        "max_abs_difference_m": float(np.nanmax(gap)),
        "differences_over_1e-12_m": int(np.count_nonzero(gap > 1e-12)),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=7)
    args = parser.parse_args()
    figures: dict[str, Any] = {}
    for name, (config, overrides) in ROBOTS.items():
        cfg = load_config(ROOT / config, [*overrides, "ik.workers=1"])
        checker, q = stage_rows(cfg)
        rand = checker.robot.random_configurations(20000, 3)
        figures[name] = {
            "stage_rows": timed(checker, q, args.repeats),
            "random": timed(checker, rand, args.repeats),
        }
        for kind, f in figures[name].items():
            print(
                f"{name:>6} {kind:>10}: {f['configurations']:>6} configurations, "
                f"compiled {f['compiled_us_per_configuration']:.2f} us, NumPy "
                f"{f['numpy_us_per_configuration']:.2f} us ({f['speedup']:.2f}x), "
                f"max difference {f['max_abs_difference_m']:.1e} m"
            )
    RESULTS.parent.mkdir(parents=True, exist_ok=True)
    record = {
        "benchmark": "clearance per configuration: compiled kernels against the NumPy code",
        "command": "python benchmarks/bench_clearance.py",
        "date": datetime.now(timezone.utc).isoformat(timespec="seconds"),
        "load_average": [round(x, 2) for x in os.getloadavg()],
        "repeats": args.repeats,
        **figures,
        "machine": {
            "python": platform.python_version(),
            "platform": platform.platform(),
            "cpus": os.cpu_count(),
        },
    }
    RESULTS.write_text(json.dumps(record, indent=2) + "\n", encoding="utf-8")
    print(f"wrote {RESULTS}")


if __name__ == "__main__":
    main()
