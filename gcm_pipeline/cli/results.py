"""Commands on a finished run directory.

``gcm show``, ``plot``, ``query``, ``export`` and ``view`` (nothing is
recomputed but the query's IK).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any

from gcm_pipeline.cli.common import cloud_line, format_top, show_in_viewer
from gcm_pipeline.cli.study_dir import best_run_for, is_study_dir, show_study
from gcm_pipeline.errors import GcmError


def add_parsers(sub: Any, common: argparse.ArgumentParser) -> None:
    """Add ``show``, ``plot``, ``query``, ``export`` and ``view`` to the ``gcm`` subcommands."""
    _add_show(sub, common)
    _add_plot(sub, common)
    _add_query(sub, common)
    _add_export(sub, common)
    _add_view(sub, common)


def _add_show(sub: Any, common: argparse.ArgumentParser) -> None:
    """``gcm show RUN_DIR``."""
    show = sub.add_parser(
        "show",
        parents=[common],
        help="print the top grasps of a run, or the summary of a study directory",
        description="A run directory: its counts and top-ranked grasps. A study directory "
        "(gcm study --out DIR): its placements, coverage, best placement, engine and "
        "timings, the top placements by coverage and where best/ (the best placement's "
        "run), study.html and coverage.png are.",
    )
    show.add_argument("run_dir", metavar="RUN_DIR", type=Path, help="run or study directory")
    show.add_argument(
        "--top", type=int, default=10, metavar="N", help="rows (grasps or placements) to show (10)"
    )


def _add_plot(sub: Any, common: argparse.ArgumentParser) -> None:
    """``gcm plot RUN_DIR``."""
    plot = sub.add_parser(
        "plot",
        parents=[common],
        help="write the plots of a run (of a study directory: coverage.png and study.html)",
    )
    plot.add_argument("run_dir", metavar="RUN_DIR", type=Path)


def _add_query(sub: Any, common: argparse.ArgumentParser) -> None:
    """``gcm query RUN_DIR --pose ...``."""
    query = sub.add_parser(
        "query",
        parents=[common],
        help="nearest reachable grasp of a run's manifold to a pose",
        description="Find the grasp of the run's continuous manifold nearest to each pose "
        "that the robot reaches (IK, collisions and approach as in the run) and print it "
        "with its joint solution. Distances: position [m] plus 0.1 m per radian of rotation. "
        "Given a study directory, the query runs on its best placement's run (best/), with a "
        "note on stderr.",
    )
    query.add_argument("run_dir", metavar="RUN_DIR", type=Path, help="run (or study) directory")
    query.add_argument(
        "--pose",
        nargs=7,
        action="append",
        required=True,
        metavar=("X", "Y", "Z", "QW", "QX", "QY", "QZ"),
        help="query pose: position [m] and unit quaternion (repeatable)",
    )
    query.add_argument(
        "--frame",
        choices=("world", "base", "object"),
        default="world",
        help="frame of the poses: world (default), the robot base or the object",
    )
    query.add_argument("--json", action="store_true", help="print the answers as JSON")


def _add_export(sub: Any, common: argparse.ArgumentParser) -> None:
    """``gcm export RUN_DIR --format ...``."""
    export = sub.add_parser(
        "export",
        parents=[common],
        help="export a run's grasps (MoveIt YAML, ROS 2 bag, Parquet, NPZ)",
    )
    export.add_argument("run_dir", metavar="RUN_DIR", type=Path)
    export.add_argument(
        "--format",
        required=True,
        choices=["moveit", "mcap", "parquet", "npz"],
        help="export format (mcap: a ROS 2 bag)",
    )
    export.add_argument(
        "--trajectory",
        action="store_true",
        help="moveit: each grasp with the arm's joint trajectory approach-grasp-retreat",
    )
    export.add_argument(
        "--top", type=int, metavar="N", help="only the N best-ranked reachable grasps"
    )
    export.add_argument("--out", metavar="FILE", help="file to write (default: inside RUN_DIR)")


def _add_view(sub: Any, common: argparse.ArgumentParser) -> None:
    """``gcm view RUN_DIR``."""
    view = sub.add_parser(
        "view", parents=[common], help="open a saved run in the live meshcat viewer"
    )
    view.add_argument("run_dir", metavar="RUN_DIR", type=Path)
    view.add_argument(
        "--no-wait",
        action="store_true",
        help="return at once; the viewer's server keeps running (its pid is printed)",
    )


def _fmt_count(v: Any) -> str:
    """A count, or a breakdown ``{reason: count}`` as ``(a 1, b 2)``."""
    if isinstance(v, dict):
        return "(" + ", ".join(f"{k} {n}" for k, n in v.items()) + ")"
    return str(v)


def _summary_clouds(summary: dict[str, Any]) -> list[tuple[str, float, dict[str, int]]]:
    """The point clouds ``summary.json`` records, as ``(name, voxel size, counts)``.

    Entries that are not what a run writes (a hand-edited summary) are left out:
    ``gcm show`` reports what it can read.
    """
    out = []
    for entry in summary.get("point_clouds") or []:
        if not isinstance(entry, dict):
            continue
        name, size, counts = entry.get("name"), entry.get("voxel_size"), entry.get("counts")
        whole = isinstance(counts, dict) and all(
            isinstance(counts.get(k), int) for k in ("read", "kept", "voxels")
        )
        if isinstance(name, str) and isinstance(size, (int, float)) and whole:
            out.append((name, float(size), counts))
    return out


def _cmd_show(args: argparse.Namespace) -> int:
    from gcm_pipeline.pipeline import top_grasps
    from gcm_pipeline.rundir.run import read_run

    if args.top < 0:
        raise GcmError(f"--top must be >= 0, got {args.top}", key="--top", value=args.top)
    if is_study_dir(args.run_dir):
        return show_study(args.run_dir, args.top)
    run = read_run(args.run_dir)
    counts = run.summary.get("counts", {})
    metric = run.summary.get("ranking", {}).get("metric", "yoshikawa")
    print(f"run {run.run_dir}")
    if counts:
        print("  " + ", ".join(f"{k} {_fmt_count(v)}" for k, v in counts.items()))
    for cloud in _summary_clouds(run.summary):
        print(f"  cloud {cloud_line(*cloud)}")
    if args.top == 0:
        return 0
    top = top_grasps(run.grasps, args.top, metric)
    print(f"top {len(top)} grasps by {metric}:")
    print(format_top(top, metric))
    return 0


def _run_base_pose(summary: dict[str, Any]) -> Any:
    """The robot base (4, 4) of a run's resolved config, or None if it has none."""
    from pydantic import ValidationError

    from gcm_pipeline.config.sections import Pose

    pose = summary.get("config", {}).get("robot", {}).get("base_pose")
    if not isinstance(pose, dict):
        return None
    try:
        return Pose(**pose).matrix()
    except (ValidationError, TypeError, ValueError):
        return None


def _cmd_plot(args: argparse.Namespace) -> int:
    from gcm_pipeline.outputs.plots import write_plots
    from gcm_pipeline.rundir.run import read_run
    from gcm_pipeline.rundir.transaction import is_project_dir

    if is_project_dir(args.run_dir, "study"):
        from gcm_pipeline.study.report import plot_study

        for p in plot_study(args.run_dir):
            print(p)
        return 0
    run = read_run(args.run_dir)
    counts = {k: v for k, v in run.summary.get("counts", {}).items() if isinstance(v, int)}
    top = run.summary.get("ranking", {}).get("top")
    if isinstance(top, list):
        counts.setdefault("top", len(top))
    paths = write_plots(
        run.grasps, run.manifold, counts, run.run_dir, base_pose=_run_base_pose(run.summary)
    )
    for p in paths:
        print(p)
    return 0


def _query_poses(values: list[list[str]], frame: str, cfg: Any) -> Any:
    """World poses (M, 4, 4) of ``--pose`` values given in ``frame``."""
    import numpy as np

    from gcm_pipeline.bounds import MAX_LENGTH
    from gcm_pipeline.errors import GeometryError
    from gcm_pipeline.geometry.dualquat import dq_from_pos_quat, dq_to_matrix

    poses = []
    for i, raw in enumerate(values, start=1):
        try:
            nums = np.array([float(v) for v in raw])
        except ValueError:
            raise GeometryError(f"--pose {i}: expected 7 numbers, got {' '.join(raw)}") from None
        if not np.isfinite(nums).all():
            raise GeometryError(f"--pose {i}: values must be finite, got {' '.join(raw)}")
        if np.abs(nums[:3]).max() > MAX_LENGTH:
            raise GeometryError(
                f"--pose {i}: position {' '.join(raw[:3])} m is outside the scene (at most "
                f"{MAX_LENGTH:g} m per coordinate)"
            )
        norm = float(np.linalg.norm(nums[3:]))
        if abs(norm - 1.0) > 1e-3:
            raise GeometryError(
                f"--pose {i}: quaternion QW QX QY QZ must have norm 1 (within 1e-3), got {norm:.6g}"
            )
        poses.append(dq_to_matrix(dq_from_pos_quat(nums[:3], nums[3:])))
    world = np.stack(poses)
    if frame == "base":
        world = cfg.robot.base_pose.matrix() @ world
    elif frame == "object":
        if cfg.object is None:
            raise GeometryError("--frame object: the run's config has no object")
        world = cfg.object.pose.matrix() @ world
    return world


def _cmd_query(args: argparse.Namespace) -> int:
    import numpy as np

    from gcm_pipeline.geometry.dualquat import dq_to_pos_quat
    from gcm_pipeline.pipeline import load_manifold

    run_dir = best_run_for(args.run_dir, "query")
    with load_manifold(run_dir) as manifold:
        poses = _query_poses(args.pose, args.frame, manifold.config)
        answer = manifold.nearest_reachable(poses)
    pos, quat = dq_to_pos_quat(np.nan_to_num(answer.dq))
    quat = np.where(quat[:, :1] < 0, -quat, quat)
    items = []
    for i in range(len(poses)):
        item: dict[str, Any] = {
            "query": [float(v) for v in args.pose[i]],
            "frame": args.frame,
            "manifold_distance": float(answer.located[i]),
            "found": bool(answer.found[i]),
        }
        if answer.found[i]:
            item.update(
                distance=float(answer.distance[i]),
                triangle=int(answer.triangle[i]),
                weights=answer.weights[i].tolist(),
                row=int(answer.vertex[i]),
                position=pos[i].tolist(),
                quaternion=quat[i].tolist(),
                q=answer.q[i].tolist(),
            )
        items.append(item)
    if args.json:
        print(json.dumps(items, indent=2))
        return 0
    reach = np.asarray(manifold.grasps.get("reachable", np.zeros(0, bool)), dtype=bool)
    print(
        f"run {run_dir} ({len(manifold)} triangles, {int(reach.sum())} of "
        f"{len(manifold.grasps)} rows reachable)"
    )
    for i, item in enumerate(items, start=1):
        q = item["query"]
        print(
            f"query {i} ({args.frame}): x {q[0]:.4f} y {q[1]:.4f} z {q[2]:.4f}, "
            f"quaternion ({q[3]:.4f}, {q[4]:.4f}, {q[5]:.4f}, {q[6]:.4f})"
        )
        print(f"  nearest manifold point    {item['manifold_distance']:.4f} m away")
        if not item["found"]:
            print("  no reachable grasp found near it")
            continue
        where = f"triangle {item['triangle']}"
        if item["row"] >= 0:
            where = f"candidate row {item['row']}, in no triangle"
        print(f"  nearest reachable grasp   {item['distance']:.4f} m away ({where}, world frame)")
        cells = [*item["position"], *item["quaternion"]]
        print("  " + "  ".join(f"{c:>9}" for c in ("x", "y", "z", "qw", "qx", "qy", "qz")))
        print("  " + "  ".join(f"{c:9.4f}" for c in cells))
        joints = "  ".join(f"q{j + 1} {v:.4f}" for j, v in enumerate(item["q"]))
        print(f"  joint solution [rad]  {joints}")
    return 0


def _cmd_export(args: argparse.Namespace) -> int:
    from gcm_pipeline.pipeline.outputs import export_run

    result = export_run(
        args.run_dir, args.format, top=args.top, out=args.out, trajectory=args.trajectory
    )
    if args.quiet:
        print(result.path)
    else:
        print(f"wrote {result.rows} grasps to {result.path}")
    return 0


def _cmd_view(args: argparse.Namespace) -> int:
    from gcm_pipeline.config.robot_spec import load_robot
    from gcm_pipeline.config.run import Config
    from gcm_pipeline.rundir.clouds import CLOUD_FILE, read_clouds
    from gcm_pipeline.rundir.run import read_run

    run = read_run(args.run_dir)
    if not isinstance(run.summary.get("config"), dict):
        raise GcmError(f"{args.run_dir}: summary.json holds no config; cannot draw the scene")
    cfg = Config.from_dict(run.summary["config"], source=str(args.run_dir / "summary.json"))
    robot = load_robot(cfg.robot.spec, cfg.robot.tool)
    if not args.quiet:
        n = int(run.grasps["reachable"].sum()) if "reachable" in run.grasps else 0
        print(f"run {run.run_dir}: {len(run.grasps)} grasps, {n} reachable")
    cloud_file = Path(args.run_dir) / CLOUD_FILE
    clouds = read_clouds(cloud_file) if cloud_file.is_file() else []
    show_in_viewer(run.grasps, run.manifold, robot, cfg, wait=not args.no_wait, clouds=clouds)
    return 0


COMMANDS = {
    "show": _cmd_show,
    "plot": _cmd_plot,
    "query": _cmd_query,
    "export": _cmd_export,
    "view": _cmd_view,
}
