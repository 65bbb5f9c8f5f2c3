"""Manifold structure on real grasp sets: coverage, simplex bounds, build time, locate.

Run from the repository root::

    python benchmarks/bench_manifold_real.py            # writes results/manifold_real.json
    python benchmarks/bench_manifold_real.py --quick    # fewer repeats, no 10,000 set, prints only

Sets: the public ACRONYM mug and table (``/work/data/acronym`` or
``$ACRONYM_EXAMPLES``, successful grasps only, read by the package's
importer, format ``acronym``), GraspGen and GraspGenX inference output
(``tests/data/graspgen/``, 18-50 grasps a set, see its README),
Contact-GraspNet predictions found under ``--data DIR`` (or
``$GCM_REAL_DATA``) as ``DIR/contact_graspnet/**/predictions_*.npz``, the
package's antipodal mug (``configs/mug_antipodal.yaml``), the box and the
bottle ring of ``configs/``, and ``synthetic_10k``: 10 ACRONYM-like
families of 1,000 grasps (tool points on 8 x 8 cm patches 5 cm from a
centre, approach into it, yaw within +-20 deg), for the build-time target.

The Contact-GraspNet files are not in the repository (NVIDIA Source Code
License, non-commercial). Public ones: github.com/FrankJIE09/contact_graspnet
``results/predictions_{1,7,12}.npz`` (commit c6ec21a; that fork's
``inference.py`` output for scenes of 7-12 segmented objects), e.g.::

    git clone https://github.com/FrankJIE09/contact_graspnet /tmp/cgn
    mkdir -p DIR/contact_graspnet && cp /tmp/cgn/results/predictions_*.npz DIR/contact_graspnet/
    python benchmarks/bench_manifold_real.py --data DIR

They are read as a user would (``format: contact_graspnet``) with the camera
looking straight down; the pose metric does not depend on the camera pose
(a rigid motion of the whole set), so neither do the figures.

Per set and structure (``families``, and ``chart`` with each projection as
the reference, all with the same bounds: the config's when it has them, else
the families' defaults derived from the data's spacing):

* ``linkable``: candidates in some triple pairwise within the bounds
  (computed here independently: KD-tree on positions, angles checked, the
  neighbour graph's triangles);
* ``in_simplex``: candidates in at least one kept triangle, and their share
  of the linkable ones (target >= 95 %);
* the longest position edge and the largest vertex-to-vertex angle of every
  kept triangle against the bounds (``inside_bounds``: every one within);
* ``build_s``: median wall time of ``build_manifold`` (target for 10,000
  candidates: < 2 s);
* ``locate_queries_per_s`` (families): ``TriangleLocator.locate`` of 10,000
  queries 5 mm / 3 deg (standard deviation per axis) off the candidates
  (target >= 10,000 queries/s), per second of wall time and of this
  process's CPU time (which other jobs on the shared machine disturb less).
"""

from __future__ import annotations

import argparse
import glob
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
from scipy.sparse import coo_matrix
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import gcm_pipeline as gcm
from gcm_pipeline.geometry.dualquat import (
    dq_angle_distance,
    dq_exp,
    dq_from_pos_quat,
    dq_mul,
    dq_translation,
)
from gcm_pipeline.manifold.build import build_manifold
from gcm_pipeline.manifold.families import BOUND_TOLERANCE, default_bounds
from gcm_pipeline.manifold.locate import TriangleLocator
from gcm_pipeline.table import GraspTable

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "benchmarks" / "results" / "manifold_real.json"
ACRONYM = Path(os.environ.get("ACRONYM_EXAMPLES", "/work/data/acronym/data/examples"))
#: GraspGen(X) inference output (tests/data/graspgen/README.md) and how its gripper frame maps
#: onto the grasp frame: the GraspGenX fork's openarm gripper (fingertips 0.068 m along +z, not
#: in the registry), GraspGen's Robotiq 2F-140 (the registry's robotiq_2f_140)
OPENARM = {"grasp_to_tool": {"xyz": [0.0, 0.0, 0.068]}}
ROBOTIQ_140 = {"gripper": "robotiq_2f_140"}
GRASPGEN = {
    "graspgen_ginger": ("ginger_grasps.yml", OPENARM),
    "graspgen_mesh": ("example_mesh_antipodal.yaml", ROBOTIQ_140),
    "graspgen_cloud": ("example_pointcloud_antipodal.yaml", ROBOTIQ_140),
    "graspgen_cloud_cf": ("example_pointcloud_collisionfree_antipodal.yaml", ROBOTIQ_140),
}
#: camera 0.8 m above the table looking straight down (any pose gives the same figures)
CAMERA = {"xyz": [0.5, 0.0, 0.8], "rpy_deg": [180.0, 0.0, 0.0]}
PROJECTIONS = ("xy", "pca", "cylindrical", "spherical")
TARGETS = {"linked_share_of_linkable": 0.95, "build_s_10k": 2.0, "locate_queries_per_s": 10_000}


def from_file(path: str | Path, fmt: str, **options: Any) -> GraspTable:
    """A grasp file read by the package's importer, as a user's config would."""
    candidates = {"source": "file", "path": str(path), "format": fmt, "frame": "world"}
    cfg = gcm.Config.model_validate(
        {"robot": {"spec": "panda"}, "candidates": {**candidates, **options}}
    )
    return gcm.generate_candidates(cfg)


def acronym(stem: str) -> GraspTable | None:
    files = sorted(glob.glob(str(ACRONYM / "grasps" / f"{stem}_*.h5")))
    if not files:
        return None
    return from_file(files[0], "acronym", success_only=True)


def contact_graspnet(data: Path | None) -> list[tuple[str, GraspTable]]:
    """``DIR/contact_graspnet/**/predictions_*.npz``, one set per file."""
    if data is None:
        return []
    files = sorted((data / "contact_graspnet").glob("**/predictions_*.npz"))
    if not files:
        print(f"contact_graspnet: no predictions_*.npz under {data / 'contact_graspnet'}")
    return [
        (
            f"cgn_{f.stem.removeprefix('predictions_')}",
            from_file(f, "contact_graspnet", camera_pose=CAMERA),
        )
        for f in files
    ]


def from_config(name: str) -> tuple[GraspTable, Any]:
    cfg = gcm.load_config(ROOT / "configs" / f"{name}.yaml")
    return gcm.generate_candidates(cfg), cfg.manifold


def synthetic(families: int = 10, per_family: int = 1000, seed: int = 0) -> GraspTable:
    rng = np.random.default_rng(seed)
    k = np.arange(families) + 0.5
    phi = np.arccos(1 - 2 * k / families)
    normals = np.column_stack(
        (
            np.sin(phi) * np.cos(np.pi * (1 + 5**0.5) * k),
            np.sin(phi) * np.sin(np.pi * (1 + 5**0.5) * k),
            np.cos(phi),
        )
    )
    out = []
    for n in normals:
        base = Rotation.align_vectors([-n], [[0.0, 0.0, 1.0]])[0]
        u = np.cross(n, [0.3, 0.5, 0.7])
        u /= np.linalg.norm(u)
        v = np.cross(n, u)
        s, t = rng.uniform(-0.04, 0.04, (2, per_family))
        pos = np.array([0.5, 0.0, 0.2]) + 0.05 * n + s[:, None] * u + t[:, None] * v
        yaw = Rotation.from_euler("z", rng.uniform(-20, 20, (per_family, 1)), degrees=True)
        xyzw = (base * yaw).as_quat()
        out.append(dq_from_pos_quat(pos, np.column_stack((xyzw[:, 3], xyzw[:, :3]))))
    return GraspTable({"dq": np.concatenate(out)})


def linkable(dq: np.ndarray, length: float, angle_deg: float) -> np.ndarray:
    """Candidates in some triple pairwise within the bounds (independent of the build)."""
    n = len(dq)
    pairs = cKDTree(dq_translation(dq)).query_pairs(length, output_type="ndarray")
    pairs = pairs[dq_angle_distance(dq[pairs[:, 0]], dq[pairs[:, 1]]) <= np.deg2rad(angle_deg)]
    a = coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(n, n)).tocsr()
    a = a + a.T
    through = np.asarray((a @ a).multiply(a).sum(axis=1)).ravel()
    return through > 0


def edges(dq: np.ndarray, tris: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(T,) longest position edge [m] and largest vertex angle [deg] of each triangle."""
    if not len(tris):
        return np.zeros(0), np.zeros(0)
    p, q = dq_translation(dq)[tris], dq[tris]
    length = np.stack(
        [np.linalg.norm(p[:, a] - p[:, b], axis=1) for a, b in ((0, 1), (1, 2), (2, 0))]
    )
    angle = np.stack([dq_angle_distance(q[:, a], q[:, b]) for a, b in ((0, 1), (1, 2), (2, 0))])
    return length.max(axis=0), np.degrees(angle.max(axis=0))


def median_time(fn: Any, repeats: int) -> float:
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return statistics.median(times)


def one(
    table: GraspTable,
    length: float,
    angle: float,
    kw: dict[str, Any],
    repeats: int,
    link: np.ndarray,
) -> dict[str, Any]:
    dq = np.asarray(table["dq"])
    try:
        m = build_manifold(table, max_edge_length=length, max_edge_angle_deg=angle, **kw)
    except gcm.GcmError as exc:
        return {"error": str(exc)}
    t = median_time(
        lambda: build_manifold(table, max_edge_length=length, max_edge_angle_deg=angle, **kw),
        repeats,
    )
    used = np.zeros(len(dq), dtype=bool)
    used[m.triangles.ravel()] = True
    longest, widest = edges(dq, m.triangles)
    out = {
        "triangles": len(m.triangles),
        "in_simplex": int(used.sum()),
        "in_simplex_share": float(used.mean()),
        "linked_share_of_linkable": float((used & link).sum() / max(link.sum(), 1)),
        "max_edge_m": float(longest.max(initial=0.0)),
        "median_edge_m": float(np.median(longest)) if len(longest) else 0.0,
        "max_angle_deg": float(widest.max(initial=0.0)),
        "median_angle_deg": float(np.median(widest)) if len(widest) else 0.0,
        "inside_bounds": bool(
            np.all(longest <= length * (1 + BOUND_TOLERANCE))
            and np.all(widest <= angle * (1 + BOUND_TOLERANCE))
        ),
        "build_s": t,
    }
    if m.isolation is not None:
        out["families"] = int(m.family.max() + 1)
        out["isolated_by_reason"] = m.isolated_counts
    return out


def locate_rate(table: GraspTable, repeats: int) -> tuple[float, float]:
    """Queries per second of wall time and of this process's CPU time (median of repeats)."""
    dq = np.asarray(table["dq"])
    m = build_manifold(table, structure="families")
    loc = TriangleLocator(dq[m.triangles])
    rng = np.random.default_rng(1)
    rows = rng.integers(0, len(dq), 10_000)
    twist = np.concatenate(
        (rng.normal(size=(10_000, 3)) * np.deg2rad(3.0), rng.normal(size=(10_000, 3)) * 0.005), 1
    )
    queries = dq_mul(dq[rows], dq_exp(twist))
    loc.locate(queries[:100])  # compile / warm up
    wall, cpu = [], []
    for _ in range(repeats):
        t0, c0 = time.perf_counter(), time.process_time()
        loc.locate(queries)
        wall.append(time.perf_counter() - t0)
        cpu.append(time.process_time() - c0)
    return 10_000 / statistics.median(wall), 10_000 / statistics.median(cpu)


def bench_set(
    name: str, table: GraspTable, section: Any, repeats: int, with_locate: bool
) -> dict[str, Any]:
    dq = np.asarray(table["dq"])
    given = (
        getattr(section, "max_edge_length", None),
        getattr(section, "max_edge_angle_deg", None),
    )
    length, angle = default_bounds(dq, 0.1, *given)
    link = linkable(dq, length, angle)
    out: dict[str, Any] = {
        "candidates": len(dq),
        "bounds": {
            "max_edge_length_m": length,
            "max_edge_angle_deg": angle,
            "from": "config" if given[0] else "spacing",
        },
        "linkable": int(link.sum()),
        "linkable_share": float(link.mean()),
        "families": one(table, length, angle, {"structure": "families"}, repeats, link),
    }
    for proj in PROJECTIONS:
        out[f"chart_{proj}"] = one(
            table, length, angle, {"structure": "chart", "projection": proj}, repeats, link
        )
    if with_locate:
        rate, cpu_rate = locate_rate(table, repeats)
        out["families"]["locate_queries_per_s"] = rate
        out["families"]["locate_queries_per_cpu_s"] = cpu_rate
        print(
            f"{name:15s} locate on the families' triangles: {rate:,.0f} queries/s "
            f"({cpu_rate:,.0f} per CPU second)"
        )
    print(
        f"{name:15s} {len(dq):6d} {length:7.4f} {angle:5.1f} {link.mean():6.1%}  "
        + "  ".join(
            f"{k.replace('chart_', '')}:{v['linked_share_of_linkable']:6.1%}/{v['build_s']:.3f}s"
            if "error" not in v
            else f"{k.replace('chart_', '')}: error"
            for k, v in out.items()
            if isinstance(v, dict) and ("build_s" in v or "error" in v)
        ),
        flush=True,
    )
    fam = out["families"]
    if "error" not in fam:
        print(
            f"{'':15s} families: {fam['triangles']} triangles, {fam['in_simplex']} of {len(dq)} "
            f"candidates in one ({fam['in_simplex_share']:.1%}); longest edge "
            f"{fam['max_edge_m']:.4f} m, widest angle {fam['max_angle_deg']:.1f} deg; "
            f"inside bounds: {fam['inside_bounds']}"
        )
    return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="fewer repeats, no 10,000 set, no JSON")
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument(
        "--data",
        type=Path,
        default=os.environ.get("GCM_REAL_DATA"),
        help="folder with contact_graspnet/**/predictions_*.npz (default: $GCM_REAL_DATA)",
    )
    args = ap.parse_args()
    repeats = 1 if args.quick else args.repeats
    sets: list[tuple[str, GraspTable, Any, bool]] = []
    for stem in ("Mug", "Table"):
        t = acronym(stem)
        if t is None:
            print(f"acronym {stem}: not found under {ACRONYM} (set ACRONYM_EXAMPLES)")
        else:
            sets.append((f"acronym_{stem.lower()}", t, None, stem == "Mug"))
    for name, (file, frame) in GRASPGEN.items():
        path = ROOT / "tests" / "data" / "graspgen" / file
        t = from_file(path, "graspgen", **frame)
        sets.append((name, t, None, False))
    sets += [(name, t, None, False) for name, t in contact_graspnet(args.data)]
    for name in ("mug_antipodal", "box", "bottle_side"):
        t, section = from_config(name)
        sets.append((name, t, section, False))
    if not args.quick:
        sets.append(("synthetic_10k", synthetic(), None, True))
    head = f"{'set':15s} {'N':>6s} {'L [m]':>7s} {'A[deg]':>5s} {'link':>6s}"
    print(f"{head}  structure: linked share of linkable / build time")
    results = {name: bench_set(name, t, s, repeats, loc) for name, t, s, loc in sets}
    if args.quick:
        return 0
    doc = {
        "benchmark": "manifold_real",
        "date": datetime.now(timezone.utc).isoformat(timespec="seconds"),
        "machine": {"platform": platform.platform(), "cpus": os.cpu_count()},
        "command": "python benchmarks/bench_manifold_real.py"
        + (" --data DIR" if args.data else ""),
        "repeats": repeats,
        "targets": TARGETS,
        **results,
    }
    RESULTS.parent.mkdir(parents=True, exist_ok=True)
    RESULTS.write_text(json.dumps(doc, indent=2) + "\n")
    print(f"wrote {RESULTS.relative_to(ROOT)}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
