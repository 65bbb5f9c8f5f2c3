"""``gcm study STUDY --out DIR``: a placement study on Ray, and its printout."""

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


COMMANDS = {"study": _cmd_study}
