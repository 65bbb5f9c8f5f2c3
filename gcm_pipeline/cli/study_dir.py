"""Results commands given a study directory instead of a run directory.

A study directory (``gcm study --out DIR``; marker kind ``study``) is not a
run: ``gcm show`` prints the study's summary (:func:`show_study`), ``gcm
query`` answers on the best placement's run ``best/`` with a note saying so
(:func:`best_run_for`). The other results commands (``plot`` aside, which
draws the study's own outputs; ``export``, ``view``) stop with one line naming
the study directory and ``best/`` (the hint of
:func:`gcm_pipeline.rundir.run.objects_hint`).
"""

from __future__ import annotations

import statistics
import sys
from pathlib import Path
from typing import Any

from gcm_pipeline.errors import InputError
from gcm_pipeline.rundir.transaction import is_project_dir

__all__ = ["best_run_for", "is_study_dir", "show_study"]


def is_study_dir(path: Path) -> bool:
    """Whether ``path`` is a study directory (its ``.gcm.json`` marker says so)."""
    return is_project_dir(path, "study")


def best_run_for(path: Path, command: str) -> Path:
    """``path`` itself, or for a study directory its ``best/`` with a note on stderr.

    Raises:
        InputError: A study directory without ``best/``.
    """
    from gcm_pipeline.rundir.run import objects_hint

    if not is_study_dir(path):
        return path
    best = path / "best"
    if not is_project_dir(best, "run"):
        raise InputError(f"not a run directory: {path}{objects_hint(path)}", path=path)
    print(
        f"note: {path} is a study directory; gcm {command} answers on its best "
        f"placement's run {best}",
        file=sys.stderr,
        flush=True,
    )
    return best


def _timings(timings: dict[str, float]) -> str:
    return ", ".join(f"{k} {v:.1f}" for k, v in timings.items())


def _engine_line(summary: Any) -> str:
    eng = summary.engine
    if not eng.workers:  # a finished study run again: nothing ran
        return f"{eng.name} {eng.mode or ''}".rstrip()
    nodes = f" on {eng.nodes} node(s)" if eng.nodes else ""
    rate = summary.placements_per_s
    text = f"{eng.name} {eng.version or ''} {eng.mode or ''}, {eng.workers} worker(s){nodes}"
    text = " ".join(text.split()).replace(" ,", ",")
    return text + (f"; {rate:.2f} placements/s" if rate else "")


def _top_lines(overview: Any, top: int) -> list[str]:
    """The ``top`` placements by coverage (ties: lower id first)."""
    from gcm_pipeline.study.overview import describe_pose

    done = [r for r in overview.rows if r.coverage is not None]
    done.sort(key=lambda r: (-r.coverage, r.id))
    lines = [f"top {min(top, len(done))} placements by coverage:"]
    for r in done[:top]:
        lines.append(
            f"  #{r.id:<5} {r.object:<12} {r.coverage:.3f}  ({r.reachable} / {r.densified})  "
            f"{describe_pose(r, overview.swept_columns())}"
        )
    return lines


def show_study(path: Path, top: int) -> int:
    """``gcm show STUDY_DIR``: the study's counts, coverage, best placement, engine and files."""
    from gcm_pipeline.study.overview import describe_pose, read_overview

    o = read_overview(path)
    s, c = o.summary, o.summary.counts
    state = "complete" if s.complete else "not complete: run the study again to finish it"
    print(f"study {o.path}" + (f" (from {s.study.source})" if s.study.source else ""))
    print(
        f"  placements  {c.finished} of {c.placements} finished ({c.failed} failed), "
        f"{c.rounds} round(s); {state}"
    )
    cov = o.coverages
    if cov:
        print(
            f"  coverage    best {max(cov):.3f}, median {statistics.median(cov):.3f} "
            f"(over {len(cov)} placements)"
        )
    b = s.best
    if b is None:
        print("  best        none: every placement failed (column 'error' of placements.csv)")
    else:
        pose = describe_pose(b.model_dump(), o.swept_columns())
        print(
            f"  best        #{b.id} {b.object}: coverage {b.coverage:.3f} "
            f"({b.reachable} / {b.densified} reachable)" + (f"; {pose}" if pose else "")
        )
        print(f"  reproduce   {b.command}")
    print(f"  engine      {_engine_line(s)}")
    if s.timings_s:
        print(f"  timings [s] {_timings(s.timings_s)}")
    if top > 0 and cov:
        print("\n".join(_top_lines(o, top)))
    _where_lines(o)
    return 0


def _where_lines(o: Any) -> None:
    """Where the best run, the report and the coverage map are (or that they are missing)."""
    if o.best_run is not None:
        print(f"best placement's run: {o.best_run}")
        print(f"  look at it  gcm show {o.best_run}  (also gcm view, query, export on it)")
        scene = o.best_run / "scene.html"
        if scene.is_file():
            print(f"  its scene   {scene.resolve().as_uri()}")
    elif o.summary.best is not None:
        print(
            f"best placement's run: missing ({o.path / 'best'}): the study did not finish or "
            f"ran with --no-best; {o.resume_command()} writes it"
        )
    if o.report is not None:
        print(f"study report: {o.report.resolve().as_uri()}")
    else:
        print(f"study report: missing ({o.path / 'study.html'})")
    if o.coverage_png is not None:
        print(f"coverage map: {o.coverage_png}")
    else:
        print(f"coverage map: missing ({o.path / 'coverage.png'})")
