"""``format: csv``: a header naming ``x,y,z,qw,qx,qy,qz`` (any order), carried columns."""

from __future__ import annotations

import csv
import re
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from gcm_pipeline.errors import InputError, clip
from gcm_pipeline.rundir.grasps_csv import check_csv_cells
from gcm_pipeline.sources.files.common import (
    check_count,
    check_positions,
    column_name,
    score_column,
    success_labels,
    width_column,
)

__all__ = ["read_csv"]

#: The pose columns a grasp CSV must have.
_CSV_POSE = ("x", "y", "z", "qw", "qx", "qy", "qz")
#: Most columns of a grasp CSV.
_MAX_CSV_COLUMNS = 1000


def _refuse_nul(path: Path, chunk: int = 1 << 22) -> None:
    """Raise InputError at the first NUL character of a CSV file.

    NumPy's strings drop trailing NULs (a cell ``0`` + NUL read as 0) and a NUL
    inside a text column would be carried into grasps.csv.
    """
    line = 1
    try:
        with path.open("rb") as fh:
            while data := fh.read(chunk):
                at = data.find(b"\0")
                if at >= 0:
                    line += data.count(b"\n", 0, at)
                    raise InputError(
                        f"{path}:{line}: NUL character in a CSV file", path=path, row=line
                    )
                line += data.count(b"\n")
    except OSError as exc:
        raise InputError(f"{path}: cannot read CSV: {clip(str(exc))}", path=path) from None


def read_csv(
    path: Path, max_count: int
) -> tuple[np.ndarray, np.ndarray | None, dict[str, np.ndarray]]:
    """Poses, ``success`` labels (or None) and carried columns of a grasp CSV file.

    Quaternions (w, x, y, z) within 1e-3 of unit norm are normalised; every
    other column is carried (integers, numbers with empty = NaN, or text); a
    ``score`` column is the grasps' quality, a finite number in every row; a
    ``width`` column the finger opening, a number >= 0 or empty in every row.
    A UTF-8 byte order mark and blank lines are ignored.
    """
    _refuse_nul(path)
    header, rows, lines = _read_csv_rows(path, max_count)
    names = _check_csv_header(path, header, rows, lines)
    # Python strings, not a fixed-width array: that is as wide as the longest cell in every cell
    cells = np.empty((len(rows), len(names)), dtype=object)
    if rows:
        cells[:] = rows
    poses = _csv_poses(path, cells, names, lines)
    success = None
    if "success" in names:
        labels = _csv_floats(path, cells[:, names.index("success")], "success", lines)
        success = success_labels(
            path, labels, len(labels), "success", lambda i: f"{path}:{lines[i]}: column 'success'"
        )
    columns: dict[str, np.ndarray] = {}
    taken: set[str] = {"source_id", "success"}
    for k, raw in enumerate(header):
        if names[k] in _CSV_POSE or names[k] == "success":
            continue
        name = column_name(path, raw, taken)
        if name == "score":  # the file's quality: numbers, one a row (an empty cell is NaN)
            scores = _csv_floats(path, cells[:, k], raw, lines, empty=np.nan)
            columns[name] = score_column(
                path, scores, len(poses), f"column {raw!r}", where=lambda i: f"{path}:{lines[i]}"
            )
            continue
        if name == "width":  # the finger opening [m]: numbers (an empty cell is unknown)
            widths = _csv_floats(path, cells[:, k], raw, lines, empty=np.nan)
            columns[name] = width_column(
                path,
                widths,
                len(poses),
                f"column {raw!r}",
                where=lambda i, raw=raw: f"{path}:{lines[i]}: column {raw!r}",
            )
            continue
        columns[name] = _csv_column(cells[:, k])
    return poses, success, columns


def _read_csv_rows(path: Path, max_count: int) -> tuple[list[str], list[list[str]], list[int]]:
    """The header, the data rows and their line numbers (blank lines skipped)."""
    rows: list[list[str]] = []
    lines: list[int] = []
    try:
        with path.open(newline="", encoding="utf-8-sig") as fh:
            reader = csv.reader(fh)
            header: list[str] | None = None
            for row in reader:
                if not any(cell.strip() for cell in row):
                    continue  # blank line
                if header is None:
                    header = row
                    if len(header) > _MAX_CSV_COLUMNS:
                        raise InputError(
                            f"{path}: header has {len(header):,} columns, at most "
                            f"{_MAX_CSV_COLUMNS} are read",
                            path=path,
                        )
                    continue
                if len(rows) >= max_count:
                    check_count(path, len(rows) + 1, max_count)
                check_csv_cells(path, reader.line_num, header, row)
                rows.append(row)
                lines.append(reader.line_num)
    except UnicodeDecodeError as exc:
        raise InputError(
            f"{path}: not UTF-8 text ({exc.reason} at byte {exc.start})", path=path
        ) from None
    except (OSError, csv.Error) as exc:
        raise InputError(f"{path}: cannot read CSV: {clip(str(exc))}", path=path) from None
    if header is None:
        raise InputError(
            f"{path}: empty CSV; expected a header row with {','.join(_CSV_POSE)}", path=path
        )
    return header, rows, lines


def _check_csv_header(
    path: Path, header: list[str], rows: list[list[str]], lines: list[int]
) -> list[str]:
    """The column names (lower case); no name twice, the pose columns there, rows as wide."""
    names = [h.strip().lower() for h in header]
    seen: set[str] = set()
    for name in names:
        if name in seen:
            raise InputError(f"{path}: the header names column {clip(name)} twice", path=path)
        seen.add(name)
    missing = [c for c in _CSV_POSE if c not in names]
    if missing:
        raise InputError(
            f"{path}: CSV header lacks column(s) {', '.join(missing)}; "
            f"expected {','.join(_CSV_POSE)} (got {clip(','.join(names))})",
            path=path,
        )
    width = len(names)
    for row, line in zip(rows, lines, strict=True):
        if len(row) != width:
            raise InputError(
                f"{path}:{line}: row has {len(row)} fields, the header has {width}",
                path=path,
                row=line,
                value=len(row),
            )
    return names


def _csv_poses(path: Path, cells: np.ndarray, names: list[str], lines: list[int]) -> np.ndarray:
    """(N, 4, 4) poses from the x, y, z, qw, qx, qy, qz cells (checked, quaternion normalised)."""
    values = np.empty((cells.shape[0], 7))
    for k, c in enumerate(_CSV_POSE):
        values[:, k] = _csv_floats(path, cells[:, names.index(c)], c, lines)
    if not np.all(np.isfinite(values)):
        i, k = (int(a[0]) for a in np.nonzero(~np.isfinite(values)))
        raise InputError(
            f"{path}:{lines[i]}: column {_CSV_POSE[k]!r}: non-finite value {float(values[i, k])}",
            path=path,
            row=lines[i],
            key=_CSV_POSE[k],
            value=float(values[i, k]),
        )
    check_positions(path, values[:, :3], lambda i: f"{path}:{lines[i]}")
    quat = values[:, 3:]
    norm = np.linalg.norm(quat, axis=1)
    bad = np.flatnonzero(np.abs(norm - 1.0) > 1e-3)
    if bad.size:
        raise InputError(
            f"{path}:{lines[int(bad[0])]}: quaternion (qw,qx,qy,qz) has norm "
            f"{norm[bad[0]]:.6g}, expected 1",
            path=path,
            row=lines[int(bad[0])],
            value=float(norm[bad[0]]),
        )
    quat = quat / norm[:, None]
    poses = np.zeros((values.shape[0], 4, 4))
    poses[:, :3, :3] = Rotation.from_quat(quat[:, [1, 2, 3, 0]]).as_matrix()
    poses[:, :3, 3] = values[:, :3]
    poses[:, 3, 3] = 1.0
    return poses


def _csv_floats(
    path: Path, col: np.ndarray, name: str, lines: list[int], empty: float | None = None
) -> np.ndarray:
    out = np.empty(len(col))
    for i, text in enumerate(col.tolist()):
        try:
            out[i] = empty if empty is not None and not text.strip() else float(text)
        except ValueError:
            raise InputError(
                f"{path}:{lines[i]}: column {name!r}: not a number: {clip(text)}",
                path=path,
                row=lines[i],
                key=name,
                value=text,
            ) from None
    return out


def _csv_column(col: np.ndarray) -> np.ndarray:
    """A carried CSV column: int64 if all integers, float64 if numbers (empty: NaN), else text.

    ``col`` holds Python strings (of at most ``MAX_CSV_CELL`` characters).
    """
    stripped = [t.strip() for t in col.tolist()]
    try:
        if stripped and all(re.fullmatch(r"[-+]?[0-9]{1,18}", t) for t in stripped):
            return np.array([int(t) for t in stripped], dtype=np.int64)
        return np.array([float(t) if t else np.nan for t in stripped], dtype=np.float64)
    except ValueError:
        return np.array(col.tolist(), dtype=str).reshape(len(stripped))
