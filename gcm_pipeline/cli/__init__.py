"""Command line: ``gcm run | validate | schema | show | plot | query | export | view | ...``.

``gcm run CONFIG`` runs the whole pipeline and writes the run directory;
``gcm validate CONFIG`` only checks a config; ``gcm schema`` prints the
config's JSON Schema; ``gcm show RUN_DIR`` prints the top-ranked grasps of a
run; ``gcm plot RUN_DIR`` writes its plots; ``gcm query RUN_DIR --pose ...``
prints the nearest reachable grasp of a run's manifold to a pose; ``gcm export
RUN_DIR --format moveit | parquet | npz`` exports its grasps; ``gcm view RUN_DIR``
opens a saved run in the live meshcat viewer (nothing is recomputed);
``gcm study STUDY --out DIR`` runs a placement study on Ray and writes the
study directory; ``gcm robot SPEC`` prints what a robot spec configures (joints,
limits, frames, tool, collision pairs) and ``--out FILE`` writes its scene.

User errors (:class:`~gcm_pipeline.errors.GcmError`) print one line
``error: <message>`` on stderr and exit with status 2 (the traceback only
with ``--debug``); anything else is a bug and keeps its traceback.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import logging
import math
import os
import shlex
import signal
import sys
import time
import traceback
import typing
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import Any

import yaml

from gcm_pipeline import interrupts
from gcm_pipeline.errors import GcmError

__all__ = ["build_parser", "main"]

log = logging.getLogger("gcm_pipeline")

EXIT_USER_ERROR = 2


class _Parser(argparse.ArgumentParser):
    """An argument parser whose usage errors are one line ``error: ...`` (exit status 2)."""

    def error(self, message: str) -> typing.NoReturn:
        """Print ``error: PROG: MESSAGE (see PROG --help)`` on stderr and exit with status 2."""
        line = " ".join(f"{self.prog}: {message}".split())
        self.exit(EXIT_USER_ERROR, f"error: {line} (see {self.prog} --help)\n")


def _common(debug_help: bool = True) -> _Parser:
    p = _Parser(add_help=False)
    p.add_argument(
        "-v",
        "--verbose",
        action="count",
        default=0,
        help="more log output (-v: info, -vv: debug)",
    )
    p.add_argument(
        "--quiet",
        "-q",
        action="store_true",
        help="no progress bars, no log output but errors; gcm run prints only the run "
        "directory's path on stdout (for scripts; with --meshcat also the viewer URL)",
    )
    p.add_argument("--debug", action="store_true", help="show tracebacks of user errors")
    return p


def build_parser() -> argparse.ArgumentParser:
    """The ``gcm`` argument parser."""
    from gcm_pipeline import __version__

    common = _common()
    parser = _Parser(
        prog="gcm",
        description="Grasp configuration manifolds: densify grasp candidates on dual "
        "quaternions, check which ones a robot reaches, rank them by manipulability.",
    )
    parser.add_argument("--version", action="version", version=f"gcm {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)

    run = sub.add_parser(
        "run", parents=[common], help="run the pipeline on a config, write a run directory"
    )
    run.add_argument("config", metavar="CONFIG", type=Path, help="YAML config file")
    run.add_argument(
        "--set",
        dest="overrides",
        metavar="KEY=VALUE",
        action="append",
        default=[],
        help="override a config key, e.g. --set ik.backend=mink (repeatable)",
    )
    run.add_argument("--out", type=Path, metavar="DIR", help="run directory (overrides output.dir)")
    run.add_argument(
        "--force", action="store_true", help="replace an existing run directory when done"
    )
    run.add_argument("--meshcat", action="store_true", help="open the live meshcat viewer")
    run.add_argument(
        "--no-wait",
        action="store_true",
        help="with --meshcat: do not wait for Ctrl-C",
    )

    val = sub.add_parser("validate", parents=[common], help="check a config and print it")
    val.add_argument("config", metavar="CONFIG", type=Path)
    val.add_argument("--set", dest="overrides", metavar="KEY=VALUE", action="append", default=[])

    sub.add_parser("schema", parents=[common], help="print the config's JSON Schema")

    show = sub.add_parser("show", parents=[common], help="print the top grasps of a run")
    show.add_argument("run_dir", metavar="RUN_DIR", type=Path)
    show.add_argument("--top", type=int, default=10, metavar="N", help="rows to show (10)")

    plot = sub.add_parser("plot", parents=[common], help="write the plots of a run")
    plot.add_argument("run_dir", metavar="RUN_DIR", type=Path)

    query = sub.add_parser(
        "query",
        parents=[common],
        help="nearest reachable grasp of a run's manifold to a pose",
        description="Find the grasp of the run's continuous manifold nearest to each pose "
        "that the robot reaches (IK, collisions and approach as in the run) and print it "
        "with its joint solution. Distances: position [m] plus 0.1 m per radian of rotation.",
    )
    query.add_argument("run_dir", metavar="RUN_DIR", type=Path)
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

    export = sub.add_parser(
        "export", parents=[common], help="export a run's grasps (MoveIt YAML, Parquet, NPZ)"
    )
    export.add_argument("run_dir", metavar="RUN_DIR", type=Path)
    export.add_argument(
        "--format", required=True, choices=["moveit", "parquet", "npz"], help="export format"
    )
    export.add_argument(
        "--top", type=int, metavar="N", help="only the N best-ranked reachable grasps"
    )
    export.add_argument("--out", metavar="FILE", help="file to write (default: inside RUN_DIR)")

    view = sub.add_parser(
        "view", parents=[common], help="open a saved run in the live meshcat viewer"
    )
    view.add_argument("run_dir", metavar="RUN_DIR", type=Path)
    view.add_argument(
        "--no-wait",
        action="store_true",
        help="return at once; the viewer's server keeps running (its pid is printed)",
    )

    study = sub.add_parser(
        "study",
        parents=[common],
        help="run a placement study (object poses, base poses, objects) on Ray",
    )
    study.add_argument("study", metavar="STUDY", type=Path, help="study YAML file")
    study.add_argument(
        "--out", type=Path, metavar="DIR", required=True, help="study directory (rerun to resume)"
    )
    study.add_argument(
        "--workers",
        type=int,
        metavar="N",
        help="Ray workers, one CPU each (default: every CPU of this machine or the cluster)",
    )
    study.add_argument(
        "--address",
        metavar="ADDR",
        help="join an existing Ray cluster (HOST:PORT, ray://HOST:PORT or auto) "
        "instead of starting Ray on this machine",
    )
    study.add_argument(
        "--force",
        action="store_true",
        help="run a study with more placements than its max_placements",
    )
    study.add_argument(
        "--no-best", action="store_true", help="do not write best/ (the best placement's run)"
    )
    robot = sub.add_parser(
        "robot",
        parents=[common],
        help="print a robot spec's joints, limits, frames, tool and collision pairs",
        description="Load a robot spec (a shipped name such as panda or ur5, or a YAML "
        "file) and print its joints (type, limits, home), its frames (base, flange, grasp "
        "frame), its tool and its self-collision pairs; --out writes an HTML scene of the "
        "robot at home with its tool and the grasp (TCP) frame drawn as a gripper glyph.",
    )
    robot.add_argument("spec", metavar="SPEC", help="robot spec: a shipped name or a YAML file")
    robot.add_argument("--out", type=Path, metavar="FILE", help="write the scene (HTML) here")
    return parser


def _setup_logging(verbose: int, quiet: bool) -> None:
    level = (
        logging.ERROR if quiet else (logging.WARNING, logging.INFO, logging.DEBUG)[min(verbose, 2)]
    )
    handler = logging.StreamHandler(sys.stderr)
    handler.setFormatter(logging.Formatter("%(levelname)s %(name)s: %(message)s"))
    for h in list(log.handlers):
        if getattr(h, "_gcm_cli", False):
            log.removeHandler(h)
    handler._gcm_cli = True  # type: ignore[attr-defined]
    log.addHandler(handler)
    log.setLevel(level)
    log.propagate = False
    logging.captureWarnings(True)


# ------------------------------------------------------------------ commands


def _fmt(v: Any, width: int = 9) -> str:
    if isinstance(v, float):
        return f"{v:{width}.4f}" if abs(v) < 1e4 else f"{v:{width}.3g}"
    return f"{v!s:>{width}}"


def _fmt_count(v: Any) -> str:
    """A count, or a breakdown ``{reason: count}`` as ``(a 1, b 2)``."""
    if isinstance(v, dict):
        return "(" + ", ".join(f"{k} {n}" for k, n in v.items()) + ")"
    return str(v)


def format_top(top: list[dict[str, Any]], metric: str = "yoshikawa") -> str:
    """A small text table of the top grasps (rank, position, quaternion, metrics)."""
    from gcm_pipeline.ranking.metrics import METRIC_COLUMNS

    if not top:
        return "  (no reachable grasp)"
    cols = ["rank", "origin", "x", "y", "z", "qw", "qx", "qy", "qz", "manipulability"]
    column = METRIC_COLUMNS.get(metric, metric)
    if column not in cols and column in top[0]:
        cols.append(column)
    widths = {"rank": 4, "origin": 12, column: max(9, len(column))}
    head = "  ".join(f"{c:>{widths.get(c, 9)}}" for c in cols)
    lines = ["  " + head]
    for item in top:
        cells = [_fmt(item.get(c, ""), widths.get(c, 9)) for c in cols]
        lines.append("  " + "  ".join(cells))
    return "\n".join(lines)


def _viewer_command(args: argparse.Namespace, out: Path) -> str:
    """The ``gcm run`` line that shows this run in the live viewer (same overrides)."""
    words = ["gcm", "run", str(args.config)]
    for assignment in args.overrides:
        words += ["--set", assignment]
    words += ["--meshcat", "--force", "--out", str(out)]
    return shlex.join(words)


def _cmd_run(args: argparse.Namespace) -> int:
    from tqdm.contrib.logging import logging_redirect_tqdm

    from gcm_pipeline.pipeline import Pipeline, unreachable_hint

    pipeline = Pipeline.from_yaml(args.config, args.overrides)
    cfg = pipeline.config
    viewer = args.meshcat or cfg.publish.meshcat
    if viewer and cfg.publish.zmq_url is None and (args.no_wait or not cfg.publish.wait):
        flag = "--no-wait" if args.no_wait else "publish.wait: false"
        raise GcmError(
            f"{flag}: the meshcat server gcm starts stops when gcm returns, so its URL "
            "would be dead; run meshcat-server yourself and set publish.zmq_url, or let "
            "gcm wait for Ctrl-C"
        )
    t0 = time.perf_counter()
    with logging_redirect_tqdm(loggers=[log]):  # log lines above the progress bar
        result = pipeline.run(
            args.out, progress=not args.quiet, force=args.force, viewer=args.meshcat
        )
    total = time.perf_counter() - t0
    run_dir = result.run_dir
    assert run_dir is not None
    if args.quiet:
        print(run_dir)
    else:
        c = result.counts
        n = max(c["densified"], 1)
        print(f"gcm run {args.config}")
        print(f"  candidates    {c['candidates']}")
        if result.grasp_frame:  # a grasp file's gripper frame: never mapped silently
            print(f"  gripper       {result.grasp_frame['describe']}")
        print(f"  triangles     {c['triangles']} ({c['triangles_dropped']} dropped)")
        print(f"  densified     {c['densified']} ({c['interpolated']} interpolated)")
        share = 100 * c["reachable"] / n
        print(f"  reachable     {c['reachable']} / {c['densified']} ({share:.1f} %)")
        if c["reachable"] == 0 and c["densified"]:
            print("  " + unreachable_hint(c["unreachable_by_reason"]))
        timings = ", ".join(f"{k} {v:.2f}" for k, v in result.timings.items())
        print(f"  timings [s]   {timings}; total {total:.2f}")
        top = result.top(min(5, cfg.ranking.top_k))
        print(f"top {len(top)} grasps by {cfg.ranking.metric}:")
        print(format_top(top, cfg.ranking.metric))
        print(f"run directory: {run_dir}")
        print("  " + ", ".join(p.name for p in result.files))
        scene = run_dir / "scene.html"
        if scene.exists():
            print(f"open the scene: {scene.as_uri()}")
        if not viewer:
            print(f"live viewer:   {_viewer_command(args, run_dir)}")
    if viewer:
        wait = cfg.publish.wait and not args.no_wait
        _open_viewer(result.grasps, result.manifold, result.robot, result.config, wait=wait)
    return 0


def _open_viewer(grasps: Any, manifold: Any, robot: Any, config: Any, *, wait: bool) -> None:
    """Publish to the live viewer; wait for Ctrl-C, or leave its server running."""
    from gcm_pipeline.outputs.live import open_viewer

    viewer = open_viewer(grasps, manifold, robot, config, detach=not wait)
    try:
        print(f"meshcat viewer: {viewer.url}", flush=True)
        if wait:
            print("press Ctrl-C to quit", flush=True)
            try:
                while True:
                    time.sleep(0.5)
            except KeyboardInterrupt:  # the way to close the viewer: not an interruption
                interrupts.clear()
                print()
        elif viewer.server_pid is not None:
            print(
                f"the viewer's server keeps running (pid {viewer.server_pid}); "
                f"stop it with: kill {viewer.server_pid}",
                flush=True,
            )
    finally:
        viewer.close()


def _cmd_validate(args: argparse.Namespace) -> int:
    from gcm_pipeline.config.run import load_config
    from gcm_pipeline.pipeline import generate_candidates, preflight
    from gcm_pipeline.robot import kernels

    cfg = load_config(args.config, args.overrides)
    with kernels.suppressed():  # a check: not worth loading (or compiling) the kernels
        preflight(cfg)
    n = len(generate_candidates(cfg))  # a grasp file is read and checked as a run reads it
    c = cfg.candidates
    obj = f"{cfg.object.shape} at {list(cfg.object.pose.xyz)}" if cfg.object else "none"
    # comments first, then the resolved config: the output is itself a valid config
    print(f"# {args.config}: ok")
    print(f"#   candidates  {c.source}" + (f" {c.path}" if c.path else "") + f": {n:,} grasps")
    print(f"#   object      {obj}")
    print(f"#   robot       {cfg.robot.spec}, ik {cfg.ik.backend}, ranking {cfg.ranking.metric}")
    print(f"#   output      {cfg.output.dir}")
    print("# resolved config (defaults filled in, paths absolute):")
    print(yaml.safe_dump(cfg.to_dict(), sort_keys=False, default_flow_style=None), end="")
    return 0


def _cmd_schema(args: argparse.Namespace) -> int:
    from gcm_pipeline.config.run import config_schema

    print(json.dumps(config_schema(), indent=2))
    return 0


def _cmd_show(args: argparse.Namespace) -> int:
    from gcm_pipeline.pipeline import top_grasps
    from gcm_pipeline.rundir.run import read_run

    if args.top < 0:
        raise GcmError(f"--top must be >= 0, got {args.top}")
    run = read_run(args.run_dir)
    counts = run.summary.get("counts", {})
    metric = run.summary.get("ranking", {}).get("metric", "yoshikawa")
    print(f"run {run.run_dir}")
    if counts:
        print("  " + ", ".join(f"{k} {_fmt_count(v)}" for k, v in counts.items()))
    if args.top == 0:
        return 0
    top = top_grasps(run.grasps, args.top, metric)
    print(f"top {len(top)} grasps by {metric}:")
    print(format_top(top, metric))
    return 0


def _cmd_plot(args: argparse.Namespace) -> int:
    from gcm_pipeline.outputs.plots import write_plots
    from gcm_pipeline.rundir.run import read_run

    run = read_run(args.run_dir)
    counts = {k: v for k, v in run.summary.get("counts", {}).items() if isinstance(v, int)}
    paths = write_plots(run.grasps, run.manifold, counts, run.run_dir)
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

    with load_manifold(args.run_dir) as manifold:
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
        f"run {args.run_dir} ({len(manifold)} triangles, {int(reach.sum())} of "
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
        print(
            f"  nearest reachable grasp   {item['distance']:.4f} m away "
            f"(triangle {item['triangle']}, world frame)"
        )
        cells = [*item["position"], *item["quaternion"]]
        print("  " + "  ".join(f"{c:>9}" for c in ("x", "y", "z", "qw", "qx", "qy", "qz")))
        print("  " + "  ".join(f"{c:9.4f}" for c in cells))
        joints = "  ".join(f"q{j + 1} {v:.4f}" for j, v in enumerate(item["q"]))
        print(f"  joint solution [rad]  {joints}")
    return 0


def _cmd_export(args: argparse.Namespace) -> int:
    from gcm_pipeline.outputs.export import export_run

    result = export_run(args.run_dir, args.format, top=args.top, out=args.out)
    if args.quiet:
        print(result.path)
    else:
        print(f"wrote {result.rows} grasps to {result.path}")
    return 0


def _cmd_view(args: argparse.Namespace) -> int:
    from gcm_pipeline.config.robot_spec import load_robot
    from gcm_pipeline.config.run import Config
    from gcm_pipeline.rundir.run import read_run

    run = read_run(args.run_dir)
    if not isinstance(run.summary.get("config"), dict):
        raise GcmError(f"{args.run_dir}: summary.json holds no config; cannot draw the scene")
    cfg = Config.from_dict(run.summary["config"], source=str(args.run_dir / "summary.json"))
    robot = load_robot(cfg.robot.spec)
    if not args.quiet:
        n = int(run.grasps["reachable"].sum()) if "reachable" in run.grasps else 0
        print(f"run {run.run_dir}: {len(run.grasps)} grasps, {n} reachable")
    _open_viewer(run.grasps, run.manifold, robot, cfg, wait=not args.no_wait)
    return 0


def _plural(n: int, word: str) -> str:
    return f"{n:,} {word}" + ("" if n == 1 else "s")


def _cmd_study(args: argparse.Namespace) -> int:
    from tqdm.contrib.logging import logging_redirect_tqdm

    from gcm_pipeline.study import Study
    from gcm_pipeline.study.store import POSE_COLUMNS

    if args.workers is not None and args.workers < 1:
        raise GcmError(f"--workers must be >= 1, got {args.workers}")
    study = Study.from_yaml(args.study)
    grid, extra = study.size()
    if not args.quiet:
        more = f" (+ up to {extra} from refinement)" if extra else ""
        print(f"gcm study {args.study}: {_plural(grid, 'placement')}{more}", flush=True)
    try:
        with logging_redirect_tqdm(loggers=[log]):
            result = study.run(
                args.out,
                workers=args.workers,
                address=args.address,
                force=args.force,
                progress=not args.quiet,
                best_run=not args.no_best,
            )
    except BaseException as exc:  # an interrupt: main() prints it and sets the status
        parts = Path(args.out) / "placements"
        if interrupts.interrupt_cause(exc) is not None and any(parts.glob("*.npz")):
            print(
                f"finished placements are kept in {args.out}; run the same command to resume",
                file=sys.stderr,
            )
        raise
    if args.quiet:
        print(result.out_dir)
        if result.best is None:  # the status says it, and one line says why
            print(
                f"error: every placement failed; see {result.out_dir / 'placements.csv'}",
                file=sys.stderr,
            )
            return EXIT_USER_ERROR
        return 0
    s = result.summary
    c = s["counts"]
    eng = s["engine"]
    where = eng.get("mode", eng["name"])
    print(
        f"  placements  {c['finished']} finished ({c['run']} run now, {c['resumed']} resumed), "
        f"{c['failed']} failed, {c['rounds']} round(s)"
    )
    rate = s.get("placements_per_s")
    if eng["workers"]:
        print(
            f"  engine      {eng['name']} {eng.get('version', '')} {where}, {eng['workers']} "
            f"worker(s) on {eng.get('nodes', 1)} node(s)"
            + (f"; {rate:.2f} placements/s" if rate else "")
        )
    else:  # a finished study run again: Ray was not started
        print(f"  engine      {eng['name']} {where}")
    for f in result.failed[:3]:
        print(f"  failed      #{f['id']}: {f['error']}")
    if len(result.failed) > 3:
        rest = len(result.failed) - 3
        print(f"  failed      ... and {rest} more (column 'error' of placements.csv)")
    best = result.best
    if best is None:
        print(
            f"error: every placement failed; see {result.out_dir / 'placements.csv'}",
            file=sys.stderr,
        )
        return EXIT_USER_ERROR
    print(
        f"best placement #{best['id']} ({best['object']}): coverage {best['coverage']:.3f} "
        f"({best['reachable']} / {best['densified']} reachable, "
        f"{best['candidates_reachable']} / {best['candidates']} candidates)"
    )
    pose = ", ".join(
        f"{k.replace('_deg', '')} {best[k]:g}" + ("°" if k.endswith("_deg") else "")
        for k in POSE_COLUMNS
        if best.get(k) is not None and math.isfinite(best[k])
    )
    print(f"  pose        {pose}")
    print(f"  reproduce   {best['command']}")
    print(f"study directory: {result.out_dir}")
    print("  " + ", ".join(p.name + ("/" if p.is_dir() else "") for p in result.files))
    return 0


def _xyz_rpy(m: Any) -> str:
    """A pose as ``xyz [..] m, rpy [..] deg``."""
    from scipy.spatial.transform import Rotation

    xyz = ", ".join(f"{v:.4f}" for v in m[:3, 3])
    rpy = ", ".join(f"{v:.1f}" for v in Rotation.from_matrix(m[:3, :3]).as_euler("xyz", True))
    return f"xyz [{xyz}] m, rpy [{rpy}] deg"


def _shape_text(shape: Any) -> str:
    if shape.shape == "box":
        size = " x ".join(f"{v:g}" for v in shape.size)
    elif shape.shape in ("cylinder", "capsule"):
        size = f"r {shape.size[0]:g} l {shape.size[1]:g}"
    elif shape.shape == "sphere":
        size = f"r {shape.size[0]:g}"
    else:
        size = f"{shape.mesh.name}" + (f" scale {shape.scale[0]:g}" if shape.scale[0] != 1 else "")
    finger = f", finger {shape.finger}" if shape.finger else ""
    return f"{shape.name} ({shape.shape} {size}{finger})"


def robot_report(robot: Any) -> list[str]:
    """The lines ``gcm robot`` prints about a robot (see :func:`_cmd_robot`)."""
    import numpy as np
    import pinocchio as pin

    from gcm_pipeline.robot.collision import CollisionChecker, gripper_links
    from gcm_pipeline.robot.urdf import frame_kind

    spec = robot.spec
    out = [
        f"robot {robot.name} ({spec.path})" + (f": {spec.description}" if spec.description else "")
    ]
    source = (
        f"example-robot-data {spec.example_robot_data!r}"
        if spec.example_robot_data
        else f"robot_descriptions {spec.robot_descriptions!r}"
        if spec.robot_descriptions
        else "URDF"
    )
    out.append(f"  model        {source}: {robot.urdf_path}")
    if robot.srdf_path is not None:
        out.append(f"               SRDF {robot.srdf_path}")
    out.append(f"  joints       {robot.nq} arm joints [rad or m]")
    width = max(len(n) for n in robot.joint_names)
    out.append(f"    {'name':<{width}}  {'type':<24}  {'lower':>8}  {'upper':>8}  {'home':>8}")
    model = robot.model
    for i, name in enumerate(robot.joint_names):
        jm = model.joints[i + 1]
        kind = "prismatic" if jm.shortname().startswith("JointModelP") else "revolute"
        if name in robot.continuous_joints:
            kind = "continuous (as revolute)"
        lo, hi, home = robot.lower[i], robot.upper[i], robot.home[i]
        out.append(f"    {name:<{width}}  {kind:<24}  {lo:8.4f}  {hi:8.4f}  {home:8.4f}")
    if robot.continuous_joints:
        out.append(
            "               continuous joints get [-2pi, 2pi] unless joint_limits gives a range"
        )
    if spec.locked_joints:
        locked = ", ".join(f"{k} = {v:g}" for k, v in spec.locked_joints.items())
        out.append(f"  locked       {locked}")
    out.append(
        f"  limit margin {spec.limit_margin:g} rad (each revolute range above shrinks by it "
        "on both sides; continuous joints keep two turns)"
    )
    fm = robot.full_model
    out.append(
        f"  frames       base {robot.urdf.root_link} (the URDF's root link; poses are in it)"
    )
    gid = robot.full_grasp_frame_id
    parent = int(fm.frames[gid].parentFrame)
    while fm.frames[parent].type != pin.FrameType.BODY and parent > 0:
        parent = int(fm.frames[parent].parentFrame)
    tool = spec.tool
    if tool is not None:
        out.append(f"               flange {tool.flange} (the tool is mounted on it)")
    home = robot.fk(robot.home)[0]
    kind = frame_kind(fm, gid)
    on = "fixed to" if kind == "link" else "on link"
    out.append(
        f"               grasp frame {robot.grasp_frame} ({kind} {on} {fm.frames[parent].name}); "
        f"at home: {_xyz_rpy(home)}"
    )
    shoulder = ", ".join(f"{v:.3f}" for v in robot.shoulder)
    out.append(f"  reach        {robot.max_reach:.3f} m from the shoulder [{shoulder}]")
    if tool is None:
        out.append("  tool         none (the grasp frame is the model's own)")
    else:
        out.append(f"  tool         {tool.name} on {tool.flange}: mount {_xyz_rpy(tool.mount)}")
        out.append(f"               TCP in the tool frame: {_xyz_rpy(tool.tcp)}")
        if tool.opening is not None:
            axis = ", ".join(f"{v:g}" for v in tool.axis)
            out.append(f"               fingers open {tool.opening:g} m along [{axis}]")
        if tool.collision:
            shapes = ", ".join(_shape_text(s) for s in tool.collision)
            out.append(f"               collision shapes: {shapes}")
        else:
            out.append(
                "               TCP only: no collision shapes, the hand is not collision-checked"
            )
    checker = CollisionChecker(robot, (), self_collision=True)
    links = checker.link_names
    kinds = np.asarray(checker.pair_kind)
    pairs = [
        p for p, k in zip(checker.geom_model.collisionPairs, kinds, strict=True) if k == "self"
    ]
    checked = {frozenset((links[int(p.first)], links[int(p.second)])) for p in pairs}
    joint_of = {
        links[i]: int(g.parentJoint)
        for i, g in enumerate(checker.geom_model.geometryObjects[: checker.n_robot_geoms])
    }
    names = sorted(set(links), key=list(links).index)
    excluded = []
    for a_i, a in enumerate(names):
        for b in names[a_i + 1 :]:
            if frozenset((a, b)) in checked:
                continue
            ja, jb = joint_of[a], joint_of[b]
            if ja == jb:
                why = "one body"
            elif model.parents[ja] == jb or model.parents[jb] == ja:
                why = "adjacent"
            else:
                why = "SRDF"
            excluded.append(f"{a}-{b} ({why})")
    grip = sorted(gripper_links(robot))
    out.append(
        f"  collision    {checker.n_robot_geoms} shapes on {len(names)} links; gripper: "
        f"{', '.join(grip) or '(none)'}"
        + (" + the tool's shapes" if tool and tool.collision else "")
    )
    out.append(
        f"               {len(pairs)} self-collision pairs checked ({len(checked)} link pairs)"
    )
    line = f"{' ' * 15}{len(excluded)} link pairs not checked:"
    for i, item in enumerate(excluded or ["(none)"]):  # whole items per line
        item += "," if i < len(excluded) - 1 else ""
        if len(line) + 1 + len(item) > 100:
            out.append(line)
            line = " " * 17 + item
        else:
            line += " " + item
    out.append(line)
    return out


def _cmd_robot(args: argparse.Namespace) -> int:
    import numpy as np

    from gcm_pipeline.config.robot_spec import load_robot
    from gcm_pipeline.config.run import Config
    from gcm_pipeline.geometry.dualquat import dq_from_matrix
    from gcm_pipeline.outputs.html import write_scene_html
    from gcm_pipeline.table import GraspTable

    robot = load_robot(args.spec)
    for line in robot_report(robot):
        print(line)
    if args.out is not None:
        spec = str(robot.spec.path)
        cfg = Config.from_dict(
            {
                "robot": {"spec": spec},
                "candidates": {"source": "file", "path": spec},
                "environment": {"table": None},
                "ranking": {"top_k": 1},
            },
            source="gcm robot",
        )
        # the grasp frame at home, drawn as the scene's gripper glyph (the robot at home)
        tcp = GraspTable(
            {
                "dq": dq_from_matrix(robot.fk(robot.home)),
                "reachable": np.ones(1, bool),
                "rank": np.ones(1, np.int64),
                "q": robot.home[None],
                "manipulability": np.ones(1),
            }
        )
        info = write_scene_html(args.out, tcp, None, robot, cfg)
        print(
            f"  scene        {args.out}: {', '.join(info.paths)} ({info.meshcat_objects} meshcat "
            "objects; the robot at home, its grasp frame drawn as a gripper glyph)"
        )
    return 0


_COMMANDS = {
    "run": _cmd_run,
    "validate": _cmd_validate,
    "schema": _cmd_schema,
    "show": _cmd_show,
    "plot": _cmd_plot,
    "query": _cmd_query,
    "export": _cmd_export,
    "view": _cmd_view,
    "study": _cmd_study,
    "robot": _cmd_robot,
}


@contextlib.contextmanager
def interrupt_on_termination() -> Iterator[None]:
    """Handle Ctrl-C, SIGTERM and SIGHUP with :func:`gcm_pipeline.interrupts.raise_interrupt`.

    Each raises :class:`~gcm_pipeline.interrupts.Terminated` (a :class:`KeyboardInterrupt`; plain
    ``KeyboardInterrupt`` for Ctrl-C) in the main thread, so every ``finally``
    and ``except BaseException`` runs: a run directory being written is
    removed. The signal is also recorded, so that an interrupt Python drops
    (raised inside a finaliser; it says nothing about it then) is raised again
    where a result becomes final (:func:`gcm_pipeline.interrupts.check`). The
    previous handlers come back afterwards. Outside the main thread the
    signals are not handled.
    """
    previous = interrupts.install()
    hook = sys.unraisablehook
    sys.unraisablehook = _quiet_dropped_interrupts(hook)
    try:
        yield
    finally:
        sys.unraisablehook = hook
        interrupts.restore(previous)


def _quiet_dropped_interrupts(hook: Any) -> Any:
    """An unraisable hook that is silent about a dropped interrupt (it is recorded)."""

    def quiet(unraisable: Any) -> None:
        if isinstance(unraisable.exc_value, KeyboardInterrupt):
            return
        hook(unraisable)

    return quiet


#: Longest error line the CLI prints [characters].
MAX_ERROR_LINE = 2000


def main(argv: Sequence[str] | None = None) -> int:
    """Run the ``gcm`` command line; returns the exit status.

    Args:
        argv: Arguments without the program name (default: ``sys.argv[1:]``).

    Returns:
        0 on success, 2 on a user error (or bad usage), 1 when a worker process
        died (e.g. killed for lack of memory), 130 on Ctrl-C, 128 +
        the signal number on SIGTERM (143) or SIGHUP (129), 141 when the
        reader of the output goes away (``gcm validate | head -1``).
    """
    parser = build_parser()
    args = parser.parse_args(argv)
    _setup_logging(args.verbose, args.quiet)
    interrupts.clear()
    try:
        with interrupt_on_termination():
            status = _COMMANDS[args.command](args)
            sys.stdout.flush()  # a closed pipe shows here, inside the handlers
            interrupts.check()  # an interrupt Python dropped on the way is not ignored
            return status
    except GcmError as exc:
        if args.debug:
            traceback.print_exc()
        message = " ".join(str(exc).split())
        if len(message) > MAX_ERROR_LINE:
            message = message[: MAX_ERROR_LINE - 3] + "..."
        print(f"error: {message}", file=sys.stderr)
        return exc.exit_status
    except BrokenPipeError:
        # the reader left (e.g. `| head`): no traceback, and none at exit either
        with contextlib.suppress(OSError, ValueError):
            devnull = os.open(os.devnull, os.O_WRONLY)
            os.dup2(devnull, sys.stdout.fileno())
        return 128 + signal.SIGPIPE
    except BaseException as exc:
        # Ctrl-C, SIGTERM, SIGHUP, also when a library wrapped it in an error of its own
        interrupt = interrupts.interrupt_cause(exc)
        if interrupt is None:
            raise
        return interrupts.report(interrupt)
    finally:
        interrupts.clear()  # a handled interrupt does not outlive the command


if __name__ == "__main__":
    sys.exit(main())
