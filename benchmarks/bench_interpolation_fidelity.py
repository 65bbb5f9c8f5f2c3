"""Interpolation fidelity on ACRONYM's public grasps: do blended grasps penetrate the object?

Run from the repository root::

    python benchmarks/bench_interpolation_fidelity.py          # results/interpolation_fidelity.json
    python benchmarks/bench_interpolation_fidelity.py --quick  # 600 rows a variant, prints only

For each ACRONYM example file (mug, table; ``/work/data/acronym/data/examples`` or
``--acronym``) the candidates are imported as a user's config imports them
(``format: acronym``, ``frame: object``: the file's mesh frame is the world), the
manifold is built and densified by the package's pipeline steps with the
``manifold`` and ``densify`` sections of ``configs/from_file.yaml``, once as that
file sets them and once for every value of every structure option the config
schema offers (``manifold.projection`` and, when the schema has it,
``manifold.structure``). Densified rows are mapped back from the robot's grasp
frame to ACRONYM's gripper frame by the inverse of the import's gripper map
(:meth:`GripperSpec.from_tool`); the candidate rows must come back to the
file's transforms (checked, to 1e-9 m / 1e-9).

Penetration of ACRONYM's Franka gripper collision mesh (its own frame, the frame of
``grasps/transforms``) with the scaled object mesh: coal's BVH collision test says
whether the surfaces cross; the depth of a crossing pose is the deepest point of
either surface inside the other solid (both meshes are watertight; surfaces
sampled every ~1.5 mm plus all vertices; ``trimesh`` inside test and closest point),
so it is a lower bound of the true depth, short by at most about the sample spacing.
A pose penetrates at tolerance ``t`` when the surfaces cross with depth > ``t``
(``t = 0``: any crossing). Successful grasps touch the object, so the headline is
``t = 1 mm``; the rate at every tolerance is reported, and as a cross-check
coal's own criterion (collision with ``security_margin = -t``).

A control shows the test sees penetration: the successful grasps moved 20 mm
further along their approach (``control_pushed_20mm``).

Rates: the vertices (distinct successful candidates used by a kept simplex all
of whose vertices are successful), every successful candidate, and the
interpolated rows whose simplex vertices are all successful (all of them, or a
uniform random sample of ``--max-rows``, seed 0; with the binomial standard error).
Every variant runs twice: on all the file's grasps (``candidates.success_only:
false``, the default: simplices with a failed vertex are not measured) and on the
successful ones only (``success_only: true``).
Target (issue 30): interpolated non-penetration rate >= 0.9 x the vertices' rate.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time
import typing
from datetime import datetime, timezone
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import coal  # noqa: E402
import h5py  # noqa: E402
import trimesh  # noqa: E402

from gcm_pipeline.config import Config  # noqa: E402
from gcm_pipeline.config.gripper_spec import load_gripper  # noqa: E402
from gcm_pipeline.config.run import read_yaml  # noqa: E402
from gcm_pipeline.config.sections import ManifoldConfig  # noqa: E402
from gcm_pipeline.geometry.dualquat import dq_to_matrix  # noqa: E402
from gcm_pipeline.geometry.meshes import read_mesh  # noqa: E402
from gcm_pipeline.pipeline import build_manifold, densify, generate_candidates  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "benchmarks" / "results" / "interpolation_fidelity.json"
BASE_CONFIG = ROOT / "configs" / "from_file.yaml"
ACRONYM = Path("/work/data/acronym/data")
SETS = {"mug": "Mug_", "table": "Table_"}
#: Manifold options that choose the structure (those the config schema has are iterated).
STRUCTURE_KEYS = ("structure", "projection")
TOLERANCES_MM = (0.0, 0.5, 1.0, 2.0, 5.0)
HEADLINE_MM = 1.0
TARGET_RATIO = 0.9
SAMPLE_SPACING = 0.0015  # [m] surface samples for the depth
PUSH = 0.02  # [m] the control: successful grasps moved this far along their approach
ANGLE_BINS_DEG = (0.0, 10.0, 20.0, 30.0, 40.0, 50.0, 180.0)
EDGE_BINS_MM = (0.0, 20.0, 40.0, 60.0, 80.0, float("inf"))


class Penetration:
    """Penetration depth of a gripper mesh posed in an object mesh's frame."""

    def __init__(self, obj_path: Path, scale: float, gripper_path: Path, seed: int = 0) -> None:
        self.obj_bvh = read_mesh(obj_path, scale)
        self.grip_bvh = read_mesh(gripper_path)
        self.obj = trimesh.load(obj_path, force="mesh")
        self.obj.apply_scale(scale)
        self.grip = trimesh.load(gripper_path, force="mesh")
        for mesh, name in ((self.obj, obj_path), (self.grip, gripper_path)):
            if not mesh.is_watertight:
                sys.exit(f"error: {name} is not watertight: the inside test needs a closed mesh")
        self.obj_pts = _surface_points(self.obj, seed)
        self.grip_pts = _surface_points(self.grip, seed + 1)
        self._eye = coal.Transform3s()

    def crosses(self, pose: np.ndarray, margin: float = 0.0) -> bool:
        """coal: do the surfaces collide (with ``security_margin``)?"""
        req = coal.CollisionRequest(coal.CollisionRequestFlag.NO_REQUEST, 1)
        req.security_margin = margin
        res = coal.CollisionResult()
        tf = coal.Transform3s(pose[:3, :3], pose[:3, 3])
        return bool(coal.collide(self.grip_bvh, tf, self.obj_bvh, self._eye, req, res))

    def depth(self, pose: np.ndarray) -> float:
        """Deepest sampled point of either surface inside the other solid [m]; -1: no contact.

        A pose whose surfaces do not cross penetrates only if one solid lies
        wholly inside the other (one vertex inside tells).
        """
        rot, t = pose[:3, :3], pose[:3, 3]
        if not self.crosses(pose):
            inside = self.obj.contains((self.grip.vertices[:1] @ rot.T) + t)[0]
            inside |= self.grip.contains((self.obj.vertices[:1] - t) @ rot)[0]
            if not inside:
                return -1.0
        g = self.grip_pts @ rot.T + t  # gripper samples in the object frame
        o = (self.obj_pts - t) @ rot  # object samples in the gripper frame
        return max(_deepest(self.obj, g), _deepest(self.grip, o), 0.0)


def _surface_points(mesh: trimesh.Trimesh, seed: int) -> np.ndarray:
    count = int(np.ceil(mesh.area / SAMPLE_SPACING**2))
    samples, _ = trimesh.sample.sample_surface_even(mesh, count, seed=seed)
    return np.concatenate((mesh.vertices, samples))


def _deepest(solid: trimesh.Trimesh, points: np.ndarray) -> float:
    lo, hi = solid.bounds
    near = points[((points >= lo) & (points <= hi)).all(axis=1)]
    if not len(near):
        return 0.0
    inside = near[solid.contains(near)]
    if not len(inside):
        return 0.0
    _, dist, _ = trimesh.proximity.closest_point(solid, inside)
    return float(dist.max())


# --------------------------------------------------------------------------- configs
def structure_options() -> dict[str, tuple[Any, ...]]:
    """The manifold's structure options in the config schema, with their choices."""
    out = {}
    for key in STRUCTURE_KEYS:
        field = ManifoldConfig.model_fields.get(key)
        if field is None:
            continue
        choices = _literal_choices(field.annotation)
        if choices:
            out[key] = choices
    return out


def _literal_choices(annotation: Any) -> tuple[Any, ...]:
    if typing.get_origin(annotation) is typing.Literal:
        return typing.get_args(annotation)
    found: list[Any] = []
    for arg in typing.get_args(annotation):  # Optional[Literal[...]], Annotated[...]
        found += [c for c in _literal_choices(arg) if c not in found]
    return tuple(found)


def variants(base_manifold: dict[str, Any]) -> list[tuple[str, dict[str, Any]]]:
    """``(label, manifold section)``: the base config's, then one per structure choice.

    A choice that gives the base config's section again is named in its label.
    """
    labels, sections = ["config"], [dict(base_manifold)]
    for key, choices in structure_options().items():
        for choice in choices:
            section = {**base_manifold, key: choice}
            if section in sections:
                i = sections.index(section)
                labels[i] += f" ({key}={choice})"
            else:
                labels.append(f"{key}={choice}")
                sections.append(section)
            if key == "structure" and choice == "families":
                # the families structure with the bounds it derives from the data
                derived = {k: v for k, v in section.items() if not k.startswith("max_edge")}
                labels.append("structure=families, derived bounds")
                sections.append(derived)
    return list(zip(labels, sections, strict=True))


def run_config(
    h5: Path, mesh: Path, scale: float, manifold: dict, dens: dict, success_only: bool
) -> Config:
    """A config that reads the file as a user's does, with these manifold and densify sections."""
    candidates = {"source": "file", "path": str(h5), "format": "acronym", "frame": "object"}
    return Config.from_dict(
        {
            "object": {"shape": "mesh", "mesh": str(mesh), "scale": scale},
            "candidates": {**candidates, "success_only": success_only},
            "manifold": manifold,
            "densify": dens,
        },
        source=str(BASE_CONFIG),
    )


# --------------------------------------------------------------------------- measuring
def to_file_frame(dq: np.ndarray, cfg: Config, report: dict[str, Any]) -> np.ndarray:
    """World grasp-frame poses (dual quaternions) -> ACRONYM gripper frame in the mesh frame."""
    spec = load_gripper(report["grasp_frame"]["gripper"])
    obj = cfg.object.pose.matrix() if cfg.object is not None else np.eye(4)
    return np.linalg.inv(obj) @ dq_to_matrix(dq) @ spec.from_tool("base")


def rates(depths: np.ndarray, crossing_margin: dict[float, np.ndarray]) -> dict[str, Any]:
    """Non-penetrating shares, one per tolerance of :data:`TOLERANCES_MM`."""
    n = len(depths)
    return {
        "count": int(n),
        "non_penetrating": [
            float(np.mean(depths <= t / 1000.0)) if n else None for t in TOLERANCES_MM
        ],
        "coal_margin_non_penetrating": [
            float(np.mean(~crossing_margin[t])) if n else None for t in TOLERANCES_MM
        ],
    }


def measure(pen: Penetration, poses: np.ndarray) -> tuple[np.ndarray, dict[float, np.ndarray]]:
    depths = np.array([pen.depth(p) for p in poses])
    coal_hits = {
        tol: np.array([pen.crosses(p, -tol / 1000.0) for p in poses], dtype=bool)
        for tol in TOLERANCES_MM
    }
    return depths, coal_hits


def simplex_rows(dense: Any, success: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Interpolated rows whose simplex vertices are all successful, and those vertices."""
    interp = np.flatnonzero(np.asarray(dense["origin"]) == "interpolated")
    verts = np.asarray(dense["vertices"], dtype=np.int64)[interp]
    used = verts >= 0  # a simplex of k < width vertices pads with -1
    good = np.where(used, success[np.where(used, verts, 0)], True).all(axis=1)
    vertex_ids = np.unique(verts[good][used[good]])
    return interp[good], vertex_ids


def bench_set(name: str, h5: Path, args: argparse.Namespace, base: dict) -> dict[str, Any]:
    with h5py.File(h5, "r") as fh:
        transforms = fh["grasps/transforms"][()]
        success_file = fh["grasps/qualities/flex/object_in_gripper"][()] == 1
        mesh = args.acronym / "examples" / fh["object/file"][()].decode()
        scale = float(fh["object/scale"][()])
    pen = Penetration(mesh, scale, args.acronym / "franka_gripper_collision_mesh.stl")
    print(f"{name}: {h5.name}: {len(transforms)} grasps, {success_file.sum()} successful")
    out: dict[str, Any] = {
        "file": h5.name,
        "mesh": str(mesh.relative_to(args.acronym)),
        "scale": scale,
        "grasps": int(len(transforms)),
        "successful": int(success_file.sum()),
        "variants": [],
    }
    ok_ids = np.flatnonzero(success_file)
    d, hits = measure(pen, transforms[ok_ids])
    out["successful_candidates"] = rates(d, hits)
    out["failed_candidates"] = rates(*measure(pen, transforms[~success_file]))
    # a control that the test sees penetration: successful grasps pushed along their approach
    pushed = transforms[ok_ids].copy()
    pushed[:, :3, 3] += PUSH * pushed[:, :3, 2]
    out[f"control_pushed_{PUSH * 1000:g}mm"] = rates(*measure(pen, pushed))
    rng = np.random.default_rng(0)
    runs = [(only, *v) for only in (False, True) for v in variants(base["manifold"])]
    for success_only, label, manifold in runs:
        label = f"{label}, success_only" if success_only else label
        cfg = run_config(h5, mesh, scale, manifold, base["densify"], success_only)
        row = bench_variant(cfg, pen, transforms, success_file, args.max_rows, rng)
        out["variants"].append({"variant": label, "success_only": success_only, **row})
        h = row["headline"]
        print(
            f"  {label:46s} simplices {row['simplices']:6d}  rows "
            f"{row['interpolated_all_successful']:6d} (measured {row['interpolated_measured']:5d})"
            f"  vertices {row['vertices']['count']:5d}  non-penetrating @1mm: vertices "
            f"{_f(h['vertices_rate'])}  interpolated {_f(h['interpolated_rate'])}  "
            f"ratio {_f(h['ratio'])}"
        )
    return out


def bench_variant(
    cfg: Config,
    pen: Penetration,
    transforms: np.ndarray,
    success_file: np.ndarray,
    max_rows: int | None,
    rng: np.random.Generator,
) -> dict[str, Any]:
    """Build, densify, map back and measure one config."""
    report: dict[str, Any] = {}
    grasps = generate_candidates(cfg, report=report)
    t1 = time.perf_counter()
    man = build_manifold(grasps, cfg)
    t2 = time.perf_counter()
    dense = densify(grasps, man, cfg)
    t3 = time.perf_counter()
    back = to_file_frame(np.asarray(dense["dq"]), cfg, report)
    src = np.asarray(dense["source_id"])
    cand = np.flatnonzero(np.asarray(dense["origin"]) == "candidate")
    err = np.abs(back[cand] - transforms[src[cand]]).max()
    if err > 1e-9:
        sys.exit(f"error: {cfg.manifold}: candidates map back {err:.3g} off the file")
    success = success_file[src[: len(grasps)]]
    rows, vertex_ids = simplex_rows(dense, success)
    many = max_rows is not None and len(rows) > max_rows
    pick = np.sort(rng.choice(rows, max_rows, replace=False) if many else rows)
    vd, vh = measure(pen, back[vertex_ids])
    rd, rh = measure(pen, back[pick])
    r_rates, v_rates = rates(rd, rh), rates(vd, vh)
    head = TOLERANCES_MM.index(HEADLINE_MM)
    v, r = v_rates["non_penetrating"][head], r_rates["non_penetrating"][head]
    ratio = _ratio(r, v)
    deep = rd[rd > HEADLINE_MM / 1000.0] * 1000.0
    tcp = dq_to_matrix(np.asarray(dense["dq"])[: len(grasps)])
    verts = np.asarray(dense["vertices"], dtype=np.int64)[pick]
    return {
        "manifold": {
            k: v for k, v in cfg.manifold.model_dump(mode="json").items() if k in STRUCTURE_KEYS
        },
        "candidates": len(grasps),
        "simplices": _simplex_count(man),
        "interpolated_rows": int(len(dense) - len(cand)),
        "interpolated_all_successful": int(len(rows)),
        "interpolated_measured": int(len(pick)),
        "vertices": v_rates,
        "interpolated": r_rates,
        "ratio": [
            _ratio(a, b)
            for a, b in zip(r_rates["non_penetrating"], v_rates["non_penetrating"], strict=True)
        ],
        "headline": {
            "vertices_rate": v,
            "interpolated_rate": r,
            "interpolated_rate_stderr": (
                None if r is None else float(np.sqrt(r * (1 - r) / len(pick)))
            ),
            "ratio": ratio,
            "target_met": ratio is not None and ratio >= TARGET_RATIO,
            "penetrating_depth_mm_median": float(np.median(deep)) if len(deep) else 0.0,
        },
        "by_simplex_angle": spread_table(
            _spread(tcp, verts, "angle"), rd, ANGLE_BINS_DEG, "max_vertex_angle_deg"
        ),
        "by_simplex_edge": spread_table(
            _spread(tcp, verts, "length") * 1000.0, rd, EDGE_BINS_MM, "longest_edge_mm"
        ),
        "roundtrip_max_error": float(err),
        "seconds": {"manifold": round(t2 - t1, 4), "densify": round(t3 - t2, 4)},
    }


def _simplex_count(man: Any) -> int:
    """Kept simplices of a manifold (``simplices`` or, for the charts, ``triangles``)."""
    for name in ("simplices", "triangles"):
        found = getattr(man, name, None)
        if found is not None:
            return int(len(np.asarray(found)))
    raise SystemExit(f"error: {type(man).__name__} has neither simplices nor triangles")


def _spread(tcp: np.ndarray, verts: np.ndarray, what: str) -> np.ndarray:
    """Per row, the largest angle [deg] or distance [m] between two of its simplex's vertices."""
    out = np.zeros(len(verts))
    k = verts.shape[1]
    for i in range(k):
        for j in range(i + 1, k):
            a, b = verts[:, i], verts[:, j]
            both = (a >= 0) & (b >= 0)
            ta, tb = tcp[np.where(both, a, 0)], tcp[np.where(both, b, 0)]
            if what == "angle":
                cos = (np.einsum("nij,nij->n", ta[:, :3, :3], tb[:, :3, :3]) - 1.0) / 2.0
                value = np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))
            else:
                value = np.linalg.norm(ta[:, :3, 3] - tb[:, :3, 3], axis=1)
            out = np.maximum(out, np.where(both, value, 0.0))
    return out


def spread_table(
    spread: np.ndarray, depths: np.ndarray, edges: tuple[float, ...], name: str
) -> dict[str, Any]:
    """Rows and their non-penetrating share (headline tolerance) per bin of ``spread``."""
    bins = np.digitize(spread, edges[1:-1])
    ok = depths <= HEADLINE_MM / 1000.0
    counts = [int(np.sum(bins == i)) for i in range(len(edges) - 1)]
    shares = [float(np.mean(ok[bins == i])) if c else None for i, c in enumerate(counts)]
    return {name: list(edges), "rows": counts, "non_penetrating": shares}


def _ratio(a: float | None, b: float | None) -> float | None:
    """``a / b``, None (null in the JSON) when either is missing or ``b`` is 0."""
    return float(a / b) if a is not None and b else None


def _f(x: float | None) -> str:
    return f"{x:7.3f}" if x is not None else "      -"


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--acronym", type=Path, default=ACRONYM, help="ACRONYM's data folder")
    parser.add_argument("--max-rows", type=int, help="measure a sample of this many rows")
    parser.add_argument("--quick", action="store_true", help="600 rows, print only")
    args = parser.parse_args(argv)
    if args.quick:
        args.max_rows = 600
    data = read_yaml(BASE_CONFIG)
    base = {"manifold": data.get("manifold", {}), "densify": data.get("densify", {})}
    started = datetime.now(timezone.utc)
    load_start = os.getloadavg()
    sets = {}
    for name, prefix in SETS.items():
        found = sorted((args.acronym / "examples" / "grasps").glob(f"{prefix}*.h5"))
        if not found:
            sys.exit(f"error: no {prefix}*.h5 under {args.acronym / 'examples' / 'grasps'}")
        sets[name] = bench_set(name, found[0], args, base)
    heads = [v["headline"] for s in sets.values() for v in s["variants"]]
    result = {
        "benchmark": "interpolation_fidelity",
        "command": "python benchmarks/bench_interpolation_fidelity.py"
        + (f" --max-rows {args.max_rows}" if args.max_rows is not None else ""),
        "date": started.isoformat(timespec="seconds"),
        "machine": {"platform": platform.platform(), "cpus": os.cpu_count()},
        "load_average": {"start": round(load_start[0], 2), "end": round(os.getloadavg()[0], 2)},
        "base_config": str(BASE_CONFIG.relative_to(ROOT)),
        "manifold": base["manifold"],
        "densify": base["densify"],
        "target_ratio": TARGET_RATIO,
        "headline_tolerance_mm": HEADLINE_MM,
        "tolerances_mm": list(TOLERANCES_MM),
        "sample_spacing_m": SAMPLE_SPACING,
        "structure_options": {k: list(v) for k, v in structure_options().items()},
        "target_met_everywhere": all(h["target_met"] for h in heads),
        "sets": sets,
    }
    print_table(sets)
    if not args.quick:
        RESULTS.parent.mkdir(parents=True, exist_ok=True)
        RESULTS.write_text(json.dumps(result, indent=2) + "\n", encoding="utf-8")
        print(f"wrote {RESULTS.relative_to(ROOT)}")


def print_table(sets: dict[str, Any]) -> None:
    cols = "  ".join(f"{t:>5g}mm" for t in TOLERANCES_MM)
    print(f"\nnon-penetrating share (vertices / interpolated, ratio) by tolerance\n{'':52s}{cols}")
    for name, s in sets.items():
        for v in s["variants"]:
            label = f"{name} {v['variant']}"
            vv = "  ".join(_f(x) for x in v["vertices"]["non_penetrating"])
            rr = "  ".join(_f(x) for x in v["interpolated"]["non_penetrating"])
            ra = "  ".join(_f(x) for x in v["ratio"])
            print(f"{label:52s}{vv}   vertices ({v['vertices']['count']})")
            print(f"{'':52s}{rr}   interpolated ({v['interpolated']['count']})")
            print(f"{'':52s}{ra}   ratio")


if __name__ == "__main__":
    main()
