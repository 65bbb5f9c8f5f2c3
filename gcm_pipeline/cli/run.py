"""``gcm run``, ``gcm validate`` and ``gcm schema``: a config in, a run directory out."""

from __future__ import annotations

import argparse
import json
import shlex
import time
from pathlib import Path
from typing import Any

import yaml

from gcm_pipeline.cli.common import cloud_line, format_top, log, show_in_viewer
from gcm_pipeline.errors import GcmError


def add_parsers(sub: Any, common: argparse.ArgumentParser) -> None:
    """Add ``run``, ``validate`` and ``schema`` to the ``gcm`` subcommands."""
    _add_run(sub, common)
    _add_validate(sub, common)
    sub.add_parser("schema", parents=[common], help="print the config's JSON Schema")


def _add_run(sub: Any, common: argparse.ArgumentParser) -> None:
    """``gcm run CONFIG``."""
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
    _add_target(run)
    run.add_argument(
        "--force", action="store_true", help="replace an existing run directory when done"
    )
    run.add_argument("--meshcat", action="store_true", help="open the live meshcat viewer")
    run.add_argument(
        "--no-wait",
        action="store_true",
        help="with --meshcat: do not wait for Ctrl-C",
    )


def _add_validate(sub: Any, common: argparse.ArgumentParser) -> None:
    """``gcm validate CONFIG``."""
    val = sub.add_parser(
        "validate",
        parents=[common],
        help="check a config (or a study file) and print it",
        description="Check a run config and print it resolved, or check a study file (its "
        "sweep, its base config, the first placement of each object) and print what "
        "gcm study would run. The kind is told by the keys: base/sweep make a study file.",
    )
    val.add_argument("config", metavar="CONFIG", type=Path, help="run config or study file")
    val.add_argument("--set", dest="overrides", metavar="KEY=VALUE", action="append", default=[])
    _add_target(val)


def _add_target(parser: argparse.ArgumentParser) -> None:
    """``--target NAME|all``: the same as ``--set target=NAME`` (a config with ``objects``)."""
    parser.add_argument(
        "--target",
        metavar="NAME",
        help="the object of 'objects' whose grasps are analysed, or all (each in turn)",
    )


def _target_override(args: argparse.Namespace) -> None:
    """Fold ``--target`` into the overrides (the viewer command repeats them)."""
    if args.target is not None:
        args.overrides = [*args.overrides, f"target={args.target}"]


def _selection_note(selection: dict[str, Any] | None) -> str:
    """`` (of N in the file: ...)`` when the run kept only some of a file's grasps."""
    if not selection or selection["kept"] >= selection["read"]:
        return ""
    why = []
    if selection["success_only"]:
        why.append("labelled successful")
    if selection["min_score"] is not None:
        why.append(f"score >= {selection['min_score']:g}")
    if selection["limit"] is not None and selection["kept"] == selection["limit"]:
        best = "the first" if selection["limit_by"] == "file order" else "the best by score"
        why.append(f"{best} {selection['limit']}")
    return f" (of {selection['read']} in the file: {', '.join(why)})"


def _triangles_line(c: dict[str, Any]) -> str:
    """The triangle count, with what it says about the candidates.

    The families structure reports how many candidates its triangles link and
    why the rest are isolated (its pruned chart triangles are only a step of
    the build); the chart structure how many triangles the bounds dropped.
    """
    if "families" not in c:
        return f"{c['triangles']} ({c['triangles_dropped']} dropped)"
    isolated = c.get("isolated_by_reason", {})
    linked = c["candidates"] - sum(isolated.values())
    why = ", ".join(f"{k} {v}" for k, v in isolated.items())
    fams = f"{c['families']} famil{'y' if c['families'] == 1 else 'ies'}"
    tail = f"; isolated: {why}" if why else ""
    return f"{c['triangles']} in {fams}; {linked} of {c['candidates']} candidates linked{tail}"


def _viewer_command(args: argparse.Namespace, out: Path) -> str:
    """The ``gcm run`` line that shows this run in the live viewer (same overrides)."""
    words = ["gcm", "run", str(args.config)]
    for assignment in args.overrides:
        words += ["--set", assignment]
    words += ["--meshcat", "--force", "--out", str(out)]
    return shlex.join(words)


def _cmd_run(args: argparse.Namespace) -> int:
    from tqdm.contrib.logging import logging_redirect_tqdm

    from gcm_pipeline.config.objects import TARGET_ALL
    from gcm_pipeline.pipeline import Pipeline, unreachable_hint

    _target_override(args)
    pipeline = Pipeline.from_yaml(args.config, args.overrides)
    cfg = pipeline.config
    if cfg.target == TARGET_ALL:
        return _run_objects(args, cfg)
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
        print(f"  candidates    {c['candidates']}{_selection_note(result.selection)}")
        if result.grasp_frame:  # a grasp file's gripper frame: never mapped silently
            print(f"  gripper       {result.grasp_frame['describe']}")
        placed = result.config.object
        if cfg.objects is not None:  # the target, the others obstacles
            others = [o.name for o in cfg.objects if o.name != cfg.target]
            print(f"  object        {cfg.target}; obstacles: {', '.join(others) or 'none'}")
        elif cfg.object is None and placed is not None and placed.mesh is not None:
            xy = ", ".join(f"{v:g}" for v in result.config.candidates.placement.xy)
            print(f"  object        {Path(placed.mesh).name} (named by the file) at [{xy}]")
        for cloud in result.clouds:
            print(f"  cloud         {cloud_line(cloud.name, cloud.voxel_size, cloud.counts)}")
        print(f"  triangles     {_triangles_line(c)}")
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
        show_in_viewer(
            result.grasps,
            result.manifold,
            result.robot,
            result.config,
            wait=wait,
            clouds=result.clouds,
        )
    return 0


def _run_objects(args: argparse.Namespace, cfg: Any) -> int:
    """``gcm run`` of a ``target: all`` config: one run directory per object."""
    from tqdm.contrib.logging import logging_redirect_tqdm

    from gcm_pipeline.pipeline import run_objects

    if args.meshcat or cfg.publish.meshcat:
        key = "--meshcat" if args.meshcat else "publish.meshcat"
        names = ", ".join(o.name for o in cfg.objects)
        raise GcmError(
            f"{key}: target: all writes one run per object ({names}), the live viewer shows "
            "one: run one with --target NAME --meshcat, or open one with gcm view "
            "OUT/objects/NAME"
        )
    with logging_redirect_tqdm(loggers=[log]):
        result = run_objects(
            cfg, args.out, progress=not args.quiet, force=args.force, source=args.config
        )
    assert result.run_dir is not None
    if args.quiet:
        print(result.run_dir)
        return 0
    print(f"gcm run {args.config} (target: all)")
    for name, sub in result.results.items():
        c = sub.counts
        share = 100 * c["reachable"] / max(c["densified"], 1)
        print(
            f"  {name:<14}{c['candidates']} candidates, reachable {c['reachable']} / "
            f"{c['densified']} ({share:.1f} %)  {sub.run_dir}"
        )
    print(f"run directory: {result.run_dir}")
    print("  " + ", ".join(p.name for p in result.files))
    return 0


def _cmd_validate(args: argparse.Namespace) -> int:
    from gcm_pipeline.cli.study import validate_study
    from gcm_pipeline.config.objects import TARGET_ALL
    from gcm_pipeline.config.run import load_config, read_yaml
    from gcm_pipeline.config.study import file_kind

    if file_kind(read_yaml(args.config), str(args.config)) == "study":
        return validate_study(args)
    from gcm_pipeline.pipeline import place_file_object, preflight, target_config
    from gcm_pipeline.pipeline.objects import target_names
    from gcm_pipeline.robot import kernels

    _target_override(args)
    given = load_config(args.config, args.overrides)
    lines: list[str] = []
    for name in target_names(given) or [None]:  # each object's run config (target: all)
        cfg = place_file_object(target_config(given, name))
        with kernels.suppressed():  # a check: not worth loading (or compiling) the kernels
            preflight(cfg, name=name)
        lines += _validate_lines(cfg, name)
    cfg = given if given.target == TARGET_ALL else cfg
    # comments first, then the resolved config: the output is itself a valid config
    print(f"# {args.config}: ok")
    print("\n".join(lines))
    robot = cfg.robot.spec + (f" with {cfg.robot.tool}" if cfg.robot.tool else "")
    print(f"#   robot       {robot}, ik {cfg.ik.backend}, ranking {cfg.ranking.metric}")
    print(f"#   output      {cfg.output.dir}")
    print("# resolved config (defaults filled in, paths absolute):")
    print(yaml.safe_dump(cfg.to_dict(), sort_keys=False, default_flow_style=None), end="")
    return 0


def _validate_lines(cfg: Any, name: str | None) -> list[str]:
    """The candidates and object lines of ``gcm validate`` (per object with ``objects``)."""
    from gcm_pipeline.pipeline import generate_candidates

    report: dict[str, Any] = {}
    n = len(generate_candidates(cfg, report=report))  # a grasp file is read as a run reads it
    c = cfg.candidates
    obj = f"{cfg.object.shape} at {list(cfg.object.pose.xyz)}" if cfg.object else "none"
    if name is not None:
        obj = f"{name}: {obj}"
        others = [o.name for o in cfg.environment.obstacles if o.name is not None]
        obj += f" (obstacles: {', '.join(others)})" if others else ""
    line = f"#   candidates  {c.source}" + (f" {c.path}" if c.path else "") + f": {n:,} grasps"
    return [line + _selection_note(report.get("selection")), f"#   object      {obj}"]


def _cmd_schema(args: argparse.Namespace) -> int:
    from gcm_pipeline.config.run import config_schema

    print(json.dumps(config_schema(), indent=2))
    return 0


COMMANDS = {"run": _cmd_run, "validate": _cmd_validate, "schema": _cmd_schema}
