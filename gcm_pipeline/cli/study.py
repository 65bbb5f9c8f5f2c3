"""``gcm study STUDY --out DIR`` (a placement study on Ray) and ``gcm validate STUDY``."""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path
from typing import Any

from gcm_pipeline import interrupts
from gcm_pipeline.cli.common import EXIT_USER_ERROR, log
from gcm_pipeline.errors import GcmError


def add_parsers(sub: Any, common: argparse.ArgumentParser) -> None:
    """Add ``study`` to the ``gcm`` subcommands."""
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


def _plural(n: int, word: str) -> str:
    return f"{n:,} {word}" + ("" if n == 1 else "s")


def _cmd_study(args: argparse.Namespace) -> int:
    from tqdm.contrib.logging import logging_redirect_tqdm

    from gcm_pipeline.study import Study
    from gcm_pipeline.study.store import POSE_COLUMNS

    if args.workers is not None and args.workers < 1:
        raise GcmError(
            f"--workers must be >= 1, got {args.workers}", key="--workers", value=args.workers
        )
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


def _axis_text(name: str, spec: Any) -> str:
    """``x 7 values 0.2 .. 0.8`` (a range) or ``yaw_deg [0, 20]`` (a list)."""
    from gcm_pipeline.config.study import RangeSpec

    if isinstance(spec, RangeSpec):
        if spec.steps == 1:
            return f"{name} [{spec.start:g}]"
        return f"{name} {spec.steps} values {spec.start:g} .. {spec.to:g}"
    return f"{name} [{', '.join(f'{v:g}' for v in spec)}]"


def _sweep_lines(plan: Any) -> list[str]:
    """One ``#   sweep`` line per swept pose, and the objects."""
    from gcm_pipeline.config.study import AXES, BoxRegion

    sweep = plan.spec.sweep
    lines = []
    for key in ("object_pose", "base_pose"):
        pose = getattr(sweep, key)
        if pose is None:
            continue
        cells = [_axis_text(a, getattr(pose, a)) for a in AXES if getattr(pose, a) is not None]
        if isinstance(pose.region, BoxRegion):
            cells.append(f"region box {list(pose.region.min)} .. {list(pose.region.max)}")
        elif pose.region is not None:
            cells.append(f"region {pose.region}")
        lines.append(f"#   {key:<12}{'; '.join(cells)}")
    names = plan.object_names
    lines.append(f"#   {'objects':<12}{', '.join(names)}")
    return lines


def _placements_line(study: Any) -> str:
    """``#   placements  98 (of 98 combinations) + up to ...; max_placements 200``."""
    plan = study.plan
    grid, extra = study.size()
    combos = len(plan.object_names)
    for pose in (plan.spec.sweep.object_pose, plan.spec.sweep.base_pose):
        if pose is not None:
            combos *= math.prod(len(v) for v in pose.axes().values())
    text = f"#   placements  {grid:,}"
    if combos != grid:
        text += f" (of {combos:,} combinations; the others lie outside the region)"
    refine = plan.spec.refine
    if extra and refine is not None:
        rounds = plan.refine_rounds()
        text += f" + up to {extra:,} from refinement ({rounds} round(s), shrink {refine.shrink:g})"
    limit = plan.spec.max_placements
    if grid + extra > limit:
        return text + f"; more than max_placements {limit:,}: gcm study needs --force"
    return text + f"; max_placements {limit:,}"


def validate_study(args: argparse.Namespace) -> int:
    """``gcm validate STUDY``: check a study file and print what ``gcm study`` would run.

    The study file, its base config with the study's ``set``, the first
    placement of each object (``gcm run``'s preflight once: robot, meshes,
    files) and the size limits are checked as ``gcm study`` checks them
    before any work; the study directory is not.
    """
    import yaml

    from gcm_pipeline.robot import kernels
    from gcm_pipeline.study import Study

    given = [f for f, v in (("--set", args.overrides), ("--target", args.target)) if v]
    if given:
        raise GcmError(
            f"{given[0]}: {args.config} is a study file; give its overrides in its 'set' key "
            "(per object: sweep.objects[].set)",
            key=given[0],
        )
    study = Study.from_yaml(args.config)
    with kernels.suppressed():  # a check: not worth loading (or compiling) the kernels
        study.check_inputs(force=True)
    plan = study.plan
    base = str(plan.base_path) if plan.base_path else "inline"
    print(f"# {args.config}: ok (a study file)")
    sets = f", set: {', '.join(plan.spec.set)}" if plan.spec.set else ""
    print(f"#   base        {base} (a valid run config{sets})")
    print("\n".join(_sweep_lines(plan)))
    print(_placements_line(study))
    cfg = plan.base_config
    robot = cfg.robot.spec + (f" with {cfg.robot.tool}" if cfg.robot.tool else "")
    print(f"#   robot       {robot}, ik {cfg.ik.backend}, ranking {cfg.ranking.metric}")
    print(f"#   run it      gcm study {args.config} --out DIR")
    print("# the study (base path absolute):")
    data = plan.spec.model_dump(mode="json", by_alias=True, exclude_none=True)
    if plan.base_path is not None:
        data["base"] = str(plan.base_path)
    print(yaml.safe_dump(data, sort_keys=False, default_flow_style=None), end="")
    return 0


COMMANDS = {"study": _cmd_study}
