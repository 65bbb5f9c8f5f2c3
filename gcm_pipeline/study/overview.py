"""A study directory read back for ``gcm show``: its summary, its placements, where things are.

:func:`read_overview` reads what a study wrote (:mod:`gcm_pipeline.study.store`)
and checks it before anything is printed: the ``.gcm.json`` marker of kind
``study``, ``placements/`` (the record of finished placements),
``summary.json`` (validated by :class:`StudySummary`: a hand-edited or
damaged file is one line naming the key) and ``placements.csv`` (the
coverage of every placement, for the median and the top placements; the
summary's best placement must be one of its rows, with that row's coverage). It
also says where the best placement's run (``best/``), ``study.html`` and
``coverage.png`` are, and which of them are missing.

Nothing is recomputed and nothing is written.
"""

from __future__ import annotations

import csv
import json
import math
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Any

from pydantic import BaseModel, ConfigDict, Field, model_validator

from gcm_pipeline.config.study import AXES
from gcm_pipeline.config.validation import validated_file
from gcm_pipeline.errors import InputError, clip
from gcm_pipeline.rundir import arrays, transaction
from gcm_pipeline.study.store import MAX_META_BYTES, POSE_COLUMNS

__all__ = ["PlacementRow", "StudyOverview", "StudySummary", "describe_pose", "read_overview"]

Count = Annotated[int, Field(strict=True, ge=0)]
Seconds = Annotated[float, Field(ge=0, allow_inf_nan=False)]
Fraction = Annotated[float, Field(ge=0, le=1, allow_inf_nan=False)]
Coordinate = Annotated[float, Field(allow_inf_nan=False)] | None


class _Open(BaseModel):
    """A section of ``summary.json``: the keys ``gcm show`` reads are checked, others kept."""

    model_config = ConfigDict(extra="allow", frozen=True)


class Counts(_Open):
    """``counts``: placements planned, finished (of them failed), resumed, run now, rounds."""

    placements: Count
    finished: Count
    failed: Count
    resumed: Count = 0
    run: Count = 0
    rounds: Count = 1

    @model_validator(mode="after")
    def _consistent(self) -> Counts:
        if self.finished > self.placements:
            raise ValueError(f"finished {self.finished} > placements {self.placements}")
        if self.failed > self.finished:
            raise ValueError(f"failed {self.failed} > finished {self.finished}")
        return self


class Engine(_Open):
    """``engine``: what ran the placements."""

    name: str
    workers: Count
    mode: str | None = None
    version: str | None = None
    nodes: Count | None = None
    startup_s: Seconds | None = None


class Best(_Open):
    """``best``: the best placement's row and the ``gcm run`` command that reproduces it."""

    id: Count
    object: str
    coverage: Fraction
    reachable: Count
    densified: Count
    command: str
    object_x: Coordinate = None
    object_y: Coordinate = None
    object_z: Coordinate = None
    object_yaw_deg: Coordinate = None
    base_x: Coordinate = None
    base_y: Coordinate = None
    base_z: Coordinate = None
    base_yaw_deg: Coordinate = None

    @model_validator(mode="after")
    def _consistent(self) -> Best:
        if self.reachable > self.densified:
            raise ValueError(f"reachable {self.reachable} > densified {self.densified}")
        return self


class StudyInfo(_Open):
    """``study``: the study file it came from."""

    source: str | None = None


class StudySummary(_Open):
    """The keys of a study's ``summary.json`` that ``gcm show`` prints."""

    study: StudyInfo = StudyInfo()
    complete: bool
    counts: Counts
    best: Best | None
    engine: Engine
    timings_s: dict[str, Seconds] = {}
    placements_per_s: Annotated[float, Field(ge=0, allow_inf_nan=False)] | None = None


@dataclass(frozen=True)
class PlacementRow:
    """One row of ``placements.csv`` as ``gcm show`` uses it.

    Attributes:
        id: The placement's id.
        object: Its object's name.
        pose: Its pose columns that have a value (``object_x``, ..., ``base_yaw_deg``).
        coverage: Reachable fraction of its densified grasps; None for a failed placement.
        reachable: Reachable grasps (None when failed).
        densified: Densified grasps (None when failed).
    """

    id: int
    object: str
    pose: dict[str, float]
    coverage: float | None
    reachable: int | None
    densified: int | None


@dataclass(frozen=True)
class StudyOverview:
    """A study directory as :func:`read_overview` found it.

    Attributes:
        path: The study directory.
        summary: ``summary.json``, checked.
        rows: ``placements.csv``'s rows, by id.
        parts: Number of files in ``placements/`` (finished placements on record).
        best_run: ``best/`` when it is a run directory, else None.
        report: ``study.html`` when present, else None.
        coverage_png: ``coverage.png`` when present, else None.
    """

    path: Path
    summary: StudySummary
    rows: list[PlacementRow]
    parts: int
    best_run: Path | None
    report: Path | None
    coverage_png: Path | None

    @property
    def coverages(self) -> list[float]:
        """Coverage of every finished placement that did not fail, by id."""
        return [r.coverage for r in self.rows if r.coverage is not None]

    def swept_columns(self) -> tuple[str, ...]:
        """The pose columns the study sweeps (``object_x``, ...); every one if unknown."""
        study = (self.summary.study.model_extra or {}).get("study")
        sweep = study.get("sweep") if isinstance(study, dict) else None
        if not isinstance(sweep, dict):
            return POSE_COLUMNS
        out = []
        for prefix in ("object", "base"):
            axes = sweep.get(f"{prefix}_pose")
            if isinstance(axes, dict):
                out += [f"{prefix}_{a}" for a in AXES if a in axes]
        return tuple(out)

    def resume_command(self) -> str:
        """The ``gcm study`` line that finishes this study (and writes ``best/``)."""
        source = self.summary.study.source or "STUDY.yaml"
        return f"gcm study {source} --out {self.path}"


#: Most bytes of ``summary.json`` / ``placements.csv`` read (a study of 1,000,000 placements).
MAX_TABLE_BYTES = 1 << 30


def read_overview(path: str | os.PathLike[str]) -> StudyOverview:
    """Read a study directory's summary and placements (see the module docstring).

    Raises:
        InputError: Not a study directory, or ``placements/``, ``summary.json``
            or ``placements.csv`` is missing or not what a study writes (one
            line naming the file and, for a bad value, the key).
    """
    study = Path(path)
    if not transaction.is_project_dir(study, "study"):
        raise InputError(f"not a study directory: {study} (no .gcm.json marker of kind study)")
    if not (study / "placements").is_dir():
        raise InputError(
            f"{study}: study directory without placements/ (the record of its finished "
            "placements): nothing to show; run the study again into it to redo them",
            path=study / "placements",
        )
    parts = sum(1 for p in (study / "placements").glob("[0-9]*.npz") if p.stem.isdigit())
    summary = _read_summary(study / "summary.json")
    rows = _read_rows(study / "placements.csv")
    _check_best(summary, rows, study)
    best = study / "best"
    report, png = study / "study.html", study / "coverage.png"
    return StudyOverview(
        study,
        summary,
        rows,
        parts,
        best if transaction.is_project_dir(best, "run") else None,
        report if report.is_file() else None,
        png if png.is_file() else None,
    )


def _check_best(summary: StudySummary, rows: list[PlacementRow], study: Path) -> None:
    """``summary.json``'s best placement is a row of ``placements.csv``, with its coverage."""
    b = summary.best
    if b is None:
        return
    row = next((r for r in rows if r.id == b.id), None)
    where = f"{study / 'summary.json'}: best placement #{b.id}"
    if row is None:
        raise InputError(f"{where} is not in placements.csv; run the study again into {study}")
    if row.coverage is None or abs(row.coverage - b.coverage) > 1e-9:
        raise InputError(
            f"{where} has coverage {b.coverage:g} but {row.coverage} in placements.csv; "
            f"run the study again into {study}"
        )


def _read_text(path: Path, what: str) -> str:
    """A regular file's text (never a pipe; bounded)."""
    if not path.exists():
        raise InputError(f"{path} is missing: {what}", path=path)
    try:
        with arrays.open_regular(path) as fh:
            raw = fh.read(MAX_TABLE_BYTES + 1)
    except OSError as exc:
        raise InputError(f"cannot read {path}: {exc.strerror or exc}", path=path) from None
    if len(raw) > MAX_TABLE_BYTES:
        raise InputError(f"{path} is larger than {MAX_TABLE_BYTES:,} bytes", path=path)
    try:
        return raw.decode("utf-8")
    except UnicodeDecodeError as exc:
        raise InputError(f"{path}: not UTF-8 text (byte {exc.start})", path=path) from None


def _read_summary(path: Path) -> StudySummary:
    what = "the study stopped before it wrote it; run the study again into its directory"
    text = _read_text(path, what)
    if len(text.encode("utf-8")) > MAX_META_BYTES:
        raise InputError(f"{path}: larger than a study's summary.json ({MAX_META_BYTES:,} bytes)")
    try:
        data = json.loads(text)
    except ValueError as exc:
        raise InputError(f"{path}: not JSON ({exc})", path=path) from None
    return validated_file(data, StudySummary, str(path), InputError)


def _number(path: Path, line: int, row: dict[str, str], key: str) -> float | None:
    cell = row.get(key)
    if cell is None or cell == "":
        return None
    try:
        value = float(cell)
    except ValueError:
        raise InputError(
            f"{path}: line {line}: {key} is not a number: {clip(cell)}", path=path, row=line
        ) from None
    if math.isnan(value):
        return None
    return value


def _count(path: Path, line: int, row: dict[str, str], key: str) -> int | None:
    """A count cell: empty, or a whole number >= 0 (not 1e999, not -3, not 2.5)."""
    value = _number(path, line, row, key)
    if value is None:
        return None
    if not math.isfinite(value) or value < 0 or value != int(value):
        raise InputError(
            f"{path}: line {line}: {key} is not a whole number >= 0: {clip(row[key])}",
            path=path,
            row=line,
        )
    return int(value)


def _read_rows(path: Path) -> list[PlacementRow]:
    text = _read_text(path, "the study stopped before it wrote it; run the study again")
    reader = csv.DictReader(text.splitlines())
    need = {"id", "object", "coverage", "reachable", "densified", "error"}
    missing = sorted(need - set(reader.fieldnames or ()))
    if missing:
        raise InputError(f"{path}: not a study's placements.csv (no column {', '.join(missing)})")
    rows = []
    for line, row in enumerate(reader, start=2):
        if None in row:  # more cells than columns
            raise InputError(f"{path}: line {line}: more cells than columns", path=path, row=line)
        pid = _number(path, line, row, "id")
        if pid is None or pid < 0 or pid != int(pid):
            raise InputError(f"{path}: line {line}: id is not a whole number >= 0: {row['id']!r}")
        cov = None if row["error"] else _number(path, line, row, "coverage")
        if cov is not None and not 0.0 <= cov <= 1.0:
            raise InputError(f"{path}: line {line}: coverage {cov!r} is not within [0, 1]")
        reach, dense = (_count(path, line, row, k) for k in ("reachable", "densified"))
        pose = {k: v for k in POSE_COLUMNS if (v := _number(path, line, row, k)) is not None}
        rows.append(
            PlacementRow(
                int(pid),
                row["object"] or "",
                pose,
                cov,
                reach,
                dense,
            )
        )
    return sorted(rows, key=lambda r: r.id)


def describe_pose(
    row: dict[str, Any] | PlacementRow, columns: tuple[str, ...] = POSE_COLUMNS
) -> str:
    """``object x 0.4, y -0.1, yaw 20°`` for a placement's pose ``columns`` that have a value."""
    pose = row.pose if isinstance(row, PlacementRow) else row
    out = []
    for prefix in ("object", "base"):
        keys = [k for k in columns if k.startswith(prefix + "_")]
        cells = []
        for k in keys:
            v = pose.get(k)
            if v is None or not math.isfinite(v):
                continue
            axis = k[len(prefix) + 1 :].replace("_deg", "")
            cells.append(f"{axis} {v:g}" + ("°" if k.endswith("_deg") else ""))
        if cells:
            out.append(f"{prefix} " + ", ".join(cells))
    return "; ".join(out)
