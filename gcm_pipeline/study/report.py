"""``study.html``: a study's coverage maps, its placements and the 3-D scene of one of them.

One self-contained page (opens from disk, no server): the coverage map per
panel (:func:`~gcm_pipeline.study.coverage.grid_panels`: per yaw, per object)
as SVG cells coloured by coverage with the value printed and the robot base
marked, a sortable table of the placements, and the meshcat scene of the best
placement (:func:`~gcm_pipeline.outputs.scene.build_scene`). A click on a cell,
a dot or a table row loads that placement's scene from the data the page
embeds per placement, read from its part file (``placements/NNNNNN.npz``):
its object and robot-base transforms, one status byte per grasp (0
reachable, else its reason) and the visual placements of the robot at its
top-ranked configuration (``q_best``). The glyphs of every grasp of an
object are drawn once (``/study_grasps/o<k>``, in the object's frame); a
placement recolours them (the ``color`` attribute) and moves them with its
object. Nothing is run again.

A damaged part is skipped with one warning naming the file; its cell says
it is missing. A study directory without ``placements/`` is refused.
"""

from __future__ import annotations

import csv
import json
import logging
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from gcm_pipeline.errors import InputError
from gcm_pipeline.rundir import transaction
from gcm_pipeline.study import coverage
from gcm_pipeline.study.report_page import render_page
from gcm_pipeline.study.report_scene import StudyScene, build_study_scene
from gcm_pipeline.study.store import POSE_COLUMNS, StudyDir, atomic_write, read_part

__all__ = ["StudyReport", "plot_study", "read_report", "write_study_html"]

log = logging.getLogger(__name__)

_NUM = ("coverage", "reachable", "densified", "best_metric", "mean_metric", "mean_manipulability")


@dataclass
class StudyReport:
    """What ``study.html`` shows, read from a study directory.

    Attributes:
        path: The study directory.
        rows: One dict per placement (``placements.csv`` fields), by id; a
            placement whose part is missing or damaged has ``missing`` set.
        parts: id -> the arrays of its part file.
        swept: ``{"object": [axes], "base": [axes]}`` (the pose keys that vary).
        best: The best placement's row (None: no placement finished).
        metric: The ranking metric's name.
        warnings: One line per part file that was skipped (the page shows them).
    """

    path: Path
    rows: list[dict[str, Any]]
    parts: dict[int, dict[str, np.ndarray]]
    swept: dict[str, list[str]]
    best: dict[str, Any] | None
    metric: str = "metric"
    warnings: list[str] = field(default_factory=list)


def _number(value: str) -> Any:
    try:
        v = float(value)
    except ValueError:
        return None
    return v if math.isfinite(v) else None


def _csv_rows(path: Path) -> dict[int, dict[str, Any]]:
    """``placements.csv`` by id ({} when it is missing or unreadable)."""
    out: dict[int, dict[str, Any]] = {}
    try:
        with open(path, encoding="utf-8", newline="") as fh:
            for rec in csv.DictReader(fh):
                if not str(rec.get("id", "")).isdigit():
                    continue
                row: dict[str, Any] = {k: v for k, v in rec.items() if k}
                for k in (*POSE_COLUMNS, *_NUM):
                    row[k] = _number(rec.get(k) or "")
                row["id"] = int(rec["id"])
                row["round"] = int(rec.get("round") or 0)
                out[row["id"]] = row
    except (OSError, ValueError, csv.Error):
        return {}
    return out


def read_report(study_dir: str | Path) -> StudyReport:
    """Read what ``study.html`` shows from a study directory.

    Raises:
        InputError: Not a study directory, or it has no finished placements
            (no ``placements/`` folder, or nothing in it and no
            ``placements.csv``).
    """
    store = StudyDir(study_dir)
    path = store.path
    if not path.is_dir():
        raise InputError(f"study directory not found: {path}")
    if not transaction.is_project_dir(path, "study"):
        raise InputError(f"not a study directory: {path} has no study marker (.gcm.json)")
    if not store.parts.is_dir():
        raise InputError(
            f"{path} has no placements/ folder (the study's finished placements): nothing to "
            "report; run gcm study into it"
        )
    listed = _csv_rows(path / "placements.csv")
    parts: dict[int, dict[str, np.ndarray]] = {}
    rows: dict[int, dict[str, Any]] = {}
    notes: list[str] = []
    for part in sorted(store.parts.glob("[0-9]*.npz")):
        if not part.stem.isdigit():
            continue
        try:
            row = read_part(part)
        except Exception as exc:  # a damaged or edited file: that placement is left out
            why = " ".join(str(exc).split()).removeprefix(f"{part}: ")[:200]
            note = f"study report: skipping {part}: {why}"
            log.warning(note)
            notes.append(note)
            continue
        parts[int(row["id"])] = row.pop("arrays")
        rows[int(row["id"])] = row
    for pid, row in listed.items():
        if pid not in rows:
            row["missing"] = f"placements/{pid:06d}.npz is missing or damaged"
            rows[pid] = row
    if not rows:
        raise InputError(f"{path / 'placements'} holds no placement: nothing to report")
    ordered = [rows[k] for k in sorted(rows)]
    ok = [r for r in ordered if not r.get("missing") and not r.get("error")]
    best = _best(ok)
    return StudyReport(path, ordered, parts, _swept(ordered), best, _metric(path), notes)


def _best(rows: Sequence[dict[str, Any]]) -> dict[str, Any] | None:
    """Highest coverage, then mean manipulability, then lowest id (the study's rule)."""
    if not rows:
        return None

    def key(r: Mapping[str, Any]) -> tuple[float, float, int]:
        m = r.get("mean_manipulability")
        m = float(m) if m is not None and math.isfinite(float(m)) else -math.inf
        return (float(r.get("coverage") or 0.0), m, -int(r["id"]))

    return max(rows, key=key)


def _swept(rows: Sequence[Mapping[str, Any]]) -> dict[str, list[str]]:
    """The pose keys whose values differ between placements."""
    out: dict[str, list[str]] = {"object": [], "base": []}
    for col in POSE_COLUMNS:
        pose, axis = col.split("_", 1)
        values = {round(float(r[col]), 9) for r in rows if r.get(col) is not None}
        if len(values) > 1:
            out[pose].append(axis)
    return out


def _metric(path: Path) -> str:
    try:
        summary = json.loads((path / "summary.json").read_text(encoding="utf-8"))
        metric = summary.get("metric")  # {"name", "column"} (older studies: the name)
        name = metric.get("name") if isinstance(metric, dict) else metric
        return str(name or "metric")
    except (OSError, ValueError, AttributeError):
        return "metric"


def plot_study(study_dir: str | Path) -> list[Path]:
    """``gcm plot STUDY_DIR``: write ``coverage.png`` and ``study.html`` again.

    Raises:
        InputError: See :func:`read_report` (nothing is written then).
    """
    report = read_report(study_dir)
    best = report.best
    title = "coverage: reachable fraction of the densified grasps"
    if best is not None:
        title += f"; best #{best['id']}: {float(best.get('coverage') or 0):.3f}"
    rows = [r for r in report.rows if not r.get("missing")]

    def draw(tmp: Path) -> None:
        coverage.write_coverage_png(
            rows, report.swept, tmp, best_id=int(best["id"]) if best else None, title=title
        )

    png = StudyDir(report.path).write_with("coverage.png", draw)
    return [png, write_study_html(report)]


def write_study_html(study: str | Path | StudyReport) -> Path:
    """Write ``study.html`` into a study directory (atomically) and return its path.

    Raises:
        InputError: See :func:`read_report`.
    """
    report = study if isinstance(study, StudyReport) else read_report(study)
    scene = build_study_scene(report)
    page = render_page(report, scene, _page_data(report, scene))
    out = report.path / "study.html"
    with atomic_write(out) as tmp:
        tmp.write_text(page, encoding="utf-8")
    return out


def _page_data(report: StudyReport, scene: StudyScene) -> dict[str, Any]:
    """The JSON the page embeds: one compact record per placement."""
    objects = scene.objects
    records = []
    for r in report.rows:
        pid = int(r["id"])
        rec: dict[str, Any] = {
            "id": pid,
            "object": str(r.get("object", "")),
            "round": int(r.get("round", 0)),
            **{k: r.get(k) for k in _NUM},
            "pose": {k: r.get(k) for k in POSE_COLUMNS},
            "error": str(r.get("error") or ""),
            "missing": str(r.get("missing") or ""),
        }
        a = report.parts.get(pid)
        if a is not None and not rec["error"]:
            rec.update(scene.placement_record(r, a))
        records.append(rec)
    return {
        "placements": records,
        "best": int(report.best["id"]) if report.best else None,
        "objects": objects,
        "classes": scene.classes,
        "metric": report.metric,
        "scene": scene.message,
        "warnings": report.warnings,
        "anyReachable": any((r.get("reachable") or 0) > 0 for r in report.rows),
    }
