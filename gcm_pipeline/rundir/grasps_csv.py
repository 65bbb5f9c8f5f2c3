"""``grasps.csv``: the grasp table as CSV, written and read back (checked).

One row per grasp, ranked rows first (rank 1 = best), then the unreachable
ones in table order. Columns, in this order: the ``csv`` cells of the column
registry :data:`~gcm_pipeline.table.COLUMNS` (``rank, origin, triangle, v1,
v2, v3, w1, w2, w3, x, y, z, qw, qx, qy, qz, reachable, reason, pos_err,
rot_err, manipulability, q1 .. q{nq}``), then any further metric columns, then
the per-candidate columns of the source
(:data:`~gcm_pipeline.table.CANDIDATE_COLUMNS`: ``score``, ``width``,
``source_id``, ...; integers as integers, strings quoted when needed). Poses
are the grasp frame in the world (quaternion with ``qw >= 0``). Floats are
written with :func:`repr` (they round-trip exactly); NaN is an empty cell;
booleans are ``true`` / ``false``.

The text is made and split in C++ (:mod:`gcm_pipeline.rundir.csv_text`:
Arrow, the same bytes as the Python writer and the same table as the Python
reader, a few seconds for a million rows); a file Arrow cannot vouch for
(quoting the writer would not write, a carriage return, any fault) is read by the Python
reader here, whose errors name the file, the line and the column.
"""

from __future__ import annotations

import csv
import re
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from gcm_pipeline.bounds import MAX_CSV_CELL
from gcm_pipeline.errors import InputError, clip
from gcm_pipeline.geometry.dualquat import dq_from_pos_quat, dq_to_pos_quat
from gcm_pipeline.rundir import csv_text
from gcm_pipeline.table import CANDIDATE_COLUMNS, COLUMNS, Column, GraspTable

__all__ = [
    "CSV_COLUMNS",
    "check_csv_cells",
    "format_floats",
    "read_grasps_csv",
    "read_grasps_csv_pose",
    "write_grasps_csv",
]

#: A per-joint cell of :attr:`~gcm_pipeline.table.Column.csv`: ``q{j}`` is ``q1 .. q{nq}``.
PER_JOINT = "{j}"

#: The leading columns of ``grasps.csv`` with fixed names, in order (then ``q1 .. q{nq}``):
#: the ``csv`` cells of :data:`~gcm_pipeline.table.COLUMNS`.
CSV_COLUMNS = tuple(c for col in COLUMNS.values() for c in col.csv if PER_JOINT not in c)

#: Table columns that grasps.csv writes among its leading columns (under the names of their cells).
_LEADING = {name: col for name, col in COLUMNS.items() if col.csv}


# ------------------------------------------------------------ grasps.csv


def format_floats(values: np.ndarray) -> list[str]:
    """Floats as :func:`repr` strings (round-trip exact); NaN as ``""``."""
    floats = np.asarray(values, dtype=float).reshape(-1).tolist()
    if not floats:
        return []
    # str() of a list reprs every float in C: ~2x faster than a comprehension
    return str(floats)[1:-1].replace("nan", "").split(", ")


def _quote(text: str) -> str:
    """A CSV field (quoted only when it has to be)."""
    if any(c in text for c in ',"\n\r'):
        return '"' + text.replace('"', '""') + '"'
    return text


def _floats(values: np.ndarray) -> Any:
    return csv_text.float_cells(values, format_floats)


def _strs(values: np.ndarray) -> Any:
    return csv_text.text_cells(values, _quote)


#: How a leading column's cells are written (Arrow text), by the registry's dtype.
_FORMATS: dict[str, Callable[[np.ndarray], Any]] = {
    "int": csv_text.int_cells,
    "float": _floats,
    "bool": csv_text.bool_cells,
    "str": _strs,
}


def _row_order(grasps: GraspTable) -> np.ndarray:
    """Ranked rows by rank, then the unranked rows in table order."""
    n = len(grasps)
    rank = grasps.get("rank")
    if rank is None:
        return np.arange(n)
    rank = np.asarray(rank, dtype=np.int64)
    key = np.where(rank > 0, rank, np.iinfo(np.int64).max)
    return np.argsort(key, kind="stable")


def _extra_columns(grasps: GraspTable) -> list[str]:
    """Further 1-D columns: metrics first, then per-candidate columns, each in table order.

    Numeric, boolean and string columns are written; per-candidate columns
    are the ones named in :data:`~gcm_pipeline.table.CANDIDATE_COLUMNS`.
    """
    extra = []
    for name in grasps.columns:
        col = grasps[name]
        if name in _LEADING or col.ndim != 1:
            continue
        if np.issubdtype(col.dtype, np.number) or col.dtype == bool or col.dtype.kind in "US":
            extra.append(name)
    return [n for n in extra if n not in CANDIDATE_COLUMNS] + [
        n for n in extra if n in CANDIDATE_COLUMNS
    ]


def _cells(values: np.ndarray) -> Any:
    """Arrow text cells of a 1-D column by dtype: bool, int, float (repr) or quoted text."""
    kind = values.dtype.kind
    if kind == "b":
        return csv_text.bool_cells(values)
    if kind in "iu":
        return csv_text.int_cells(values)
    if kind in "US":
        return _strs(values)
    return _floats(values)


def write_grasps_csv(grasps: GraspTable, path: str | Path) -> np.ndarray:
    """Write the grasp table as ``grasps.csv`` (see the module docstring).

    Args:
        grasps: The table; ``dq`` is required, every other column optional
            (missing ones are empty cells).
        path: The file to write.

    Returns:
        (N,) the table row written as each data row of the file (ranked first).
        The ``v1, v2, v3`` cells name data rows of this file (0-based, the
        header not counted), not table rows.
    """
    order = _row_order(grasps)
    extra = _extra_columns(grasps)
    written = [c for c in grasps.columns if c in _LEADING or c in extra]
    g = GraspTable({c: grasps[c] for c in written}).take(order)  # not q_pregrasp, solutions ...
    n = len(g)
    csv_row = np.empty(n, dtype=np.int64)
    csv_row[order] = np.arange(n)
    header: list[str] = []
    cols: list[tuple[Callable[[np.ndarray], Any], np.ndarray | None]] = []
    for name, spec in _LEADING.items():
        values = _leading_values(g, name, csv_row)
        cells = list(spec.csv)
        if PER_JOINT in spec.csv[0]:  # one cell per joint; none when the table has no q
            width = 0 if values is None else values.shape[1]
            cells = [spec.csv[0].format(j=j + 1) for j in range(width)]
        header += cells
        fmt = _FORMATS[spec.dtype]
        cols += [(fmt, None if values is None else values[:, k]) for k in range(len(cells))]
    for name in extra:
        header.append(name)
        cols.append((_cells, np.asarray(g[name])))
    with Path(path).open("wb") as fh:
        fh.write((",".join(header) + "\n").encode("utf-8"))
        for start in range(0, n, csv_text.CHUNK_ROWS):
            part = slice(start, min(start + csv_text.CHUNK_ROWS, n))
            size = part.stop - part.start
            csv_text.write_rows(
                fh,
                [csv_text.empty_cells(size) if v is None else fmt(v[part]) for fmt, v in cols],
            )
    return order


def _leading_values(g: GraspTable, name: str, csv_row: np.ndarray) -> np.ndarray | None:
    """(N, cells) values of a leading column as written; None when the table lacks it.

    ``dq`` is written as position and quaternion (``qw >= 0``), ``vertices``
    as the data rows of the file that hold them.
    """
    n = len(g)
    if name not in g:
        return None
    if name == "dq":
        pos, quat = dq_to_pos_quat(g["dq"])
        quat = np.where(quat[:, :1] < 0, -quat, quat)  # same rotation, qw >= 0
        return np.column_stack([pos, quat]).reshape(n, 7)
    values = np.asarray(g[name])
    values = values.reshape(n, values.shape[1] if values.ndim >= 2 else 1)
    if name == "vertices":  # table rows -> the data rows of this file that hold them
        vert = values.astype(np.int64)
        ok = (vert >= 0) & (vert < n)
        return np.where(ok, csv_row[np.where(ok, vert, 0)], vert)
    return values


def read_grasps_csv(path: str | Path) -> GraspTable:
    """Read ``grasps.csv`` back into a grasp table (``dq`` rebuilt from x..qz).

    Rows stay in file order (ranked first), so ``vertices`` (from ``v1, v2,
    v3``) index the table's rows. Columns: ``dq``, ``rank``, ``origin``,
    ``triangle``, ``vertices``, ``weights``, ``reachable``, ``reason``,
    ``pos_err``, ``rot_err``, ``manipulability``, ``q`` (the leading columns of
    :data:`~gcm_pipeline.table.COLUMNS`, parsed by their dtype) and the further
    columns, as far as the file has them (the blended candidate columns
    ``score`` and ``width`` as floats, empty = NaN).

    The file is checked as it is read: unit quaternions, finite positions,
    ``true``/``false`` switches, integer ids, ``v1..v3`` that name rows of the
    file; a UTF-8 byte order mark and blank lines are ignored.

    Raises:
        InputError: Missing file or columns, or a value that does not parse
            (names the line and column; attributes ``path``, ``row``: the line,
            ``key``: the column, ``value``: the cell).
    """
    return read_grasps_csv_pose(path)[0]


def read_grasps_csv_pose(path: str | Path) -> tuple[GraspTable, np.ndarray]:
    """:func:`read_grasps_csv` and the (N, 7) ``x, y, z, qw, qx, qy, qz`` cells as written.

    (``dq`` rebuilt from them may differ from them by an ulp.)
    """
    path = Path(path)
    split = csv_text.read_text_columns(path)
    if split is not None and all(c in split[0] for c in COLUMNS["dq"].csv):
        # Arrow's split; any doubt or fault: Python's reader, which names it
        try:
            return _table(csv_text.ArrowCells(path, *split))
        except (csv_text.Fallback, InputError):
            pass
    return _table(_Cells(path, *_read_rows(path)))


def _table(cells: _Cells | csv_text.ArrowCells) -> tuple[GraspTable, np.ndarray]:
    """The grasp table of the cells (checked) and its pose cells (N, 7)."""
    pose = cells.parse(list(COLUMNS["dq"].csv), "float")
    cols: dict[str, Any] = {"dq": _read_pose(cells, pose)}
    for name, spec in _LEADING.items():
        if name == "dq":
            continue
        names = _cell_names(spec, cells.header)
        if names and all(c in cells.raw for c in names):
            cols[name] = _read_leading(cells, name, spec, names, cols)
    for name in cells.header:
        if name in CSV_COLUMNS or name in cols or _is_per_joint(name):
            continue
        if CANDIDATE_COLUMNS.get(name) == "blend":  # score, width: floats by contract
            cols[name] = cells.floats(name)
            continue
        cols[name] = cells.column(name, _parse_column)
    return GraspTable(cols), pose.reshape(cells.n, 7)


class _Cells(csv_text.ColumnsByType):
    """The text cells of a ``grasps.csv`` by column, parsed with the line of a bad one named."""

    def __init__(self, path: Path, header: list[str], body: list[list[str]], lines: list[int]):
        self.path, self.header, self.lines, self.n = path, header, lines, len(body)
        # Python strings: a fixed-width array is as wide as the longest cell in every cell
        cells = np.empty((self.n, len(header)), dtype=object)
        if body:
            cells[:] = body
        self.raw = {name: cells[:, k] for k, name in enumerate(header)}

    def bad(self, name: str, i: int, what: str) -> InputError:
        """The error of the cell of column ``name`` in data row ``i``."""
        text = str(self.raw[name][i])
        return InputError(
            f"{self.path}:{self.lines[i]}: column {name!r}: {what}: {clip(text)}",
            path=self.path,
            row=self.lines[i],
            key=name,
            value=text,
        )

    def floats(self, name: str) -> np.ndarray:
        """A float column (an empty cell is NaN)."""
        col = np.where(self.raw[name] == "", "nan", self.raw[name])
        try:
            return col.astype(float)
        except ValueError:
            for i, text in enumerate(col.tolist()):
                try:
                    float(text)
                except ValueError:
                    raise self.bad(name, i, "not a number") from None
            raise  # pragma: no cover

    def ints(self, name: str) -> np.ndarray:
        """An integer column (no empty cells)."""
        col = self.raw[name]
        ok = np.array([re.fullmatch(r"-?[0-9]{1,18}", t) is not None for t in col.tolist()])
        if self.n and not ok.all():
            raise self.bad(name, int(np.flatnonzero(~ok)[0]), "not an integer")
        return col.astype(np.int64).reshape(self.n)

    def switches(self, name: str) -> np.ndarray:
        """A boolean column of ``true`` / ``false`` cells."""
        odd = ~np.isin(self.raw[name], ("true", "false"))
        if odd.any():
            raise self.bad(name, int(np.flatnonzero(odd)[0]), "not true or false")
        return np.asarray(self.raw[name] == "true", dtype=bool)

    def text(self, name: str) -> np.ndarray:
        """A string column."""
        return self.raw[name].astype(str)

    def column(self, name: str, parse: Callable[[Any], np.ndarray]) -> np.ndarray:
        """A further column, as ``parse`` reads it."""
        return parse(self.raw[name])


def _read_pose(cells: _Cells | csv_text.ArrowCells, pose: np.ndarray) -> np.ndarray:
    """``dq`` from the x, y, z, qw, qx, qy, qz cells (finite position, unit quaternion)."""
    n, path = cells.n, cells.path
    pose = pose.reshape(n, 7)
    pos, quat = pose[:, :3], pose[:, 3:]
    broken = ~np.isfinite(pos).all(axis=1) | ~np.isfinite(quat).all(axis=1)
    with np.errstate(invalid="ignore"):
        broken |= np.abs(np.linalg.norm(quat, axis=1) - 1.0) > 1e-6
    if broken.any():
        i = int(np.flatnonzero(broken)[0])
        raise InputError(
            f"{path}:{cells.lines[i]}: not a pose: x,y,z must be finite and qw,qx,qy,qz a unit "
            f"quaternion, got {pos[i].tolist()} and {quat[i].tolist()}",
            path=path,
            row=cells.lines[i],
            value=pose[i].tolist(),
        )
    return dq_from_pos_quat(pos.reshape(n, 3), quat.reshape(n, 4))


def _read_leading(
    cells: _Cells | csv_text.ArrowCells,
    name: str,
    spec: Column,
    names: list[str],
    cols: dict[str, Any],
) -> np.ndarray:
    """A leading column parsed by its dtype and checked (ids, rows, a reachable one's ``q``)."""
    values = cells.parse(names, spec.dtype)
    if PER_JOINT in spec.csv[0]:
        values = values.reshape(cells.n, len(names))
    if name == "rank" and (values < 0).any():
        raise cells.bad("rank", int(np.flatnonzero(values < 0)[0]), "negative")
    if name == "origin":
        odd = ~np.isin(values, ("candidate", "interpolated", ""))
        if odd.any():
            raise cells.bad("origin", int(np.flatnonzero(odd)[0]), "not candidate or interpolated")
    if name == "vertices":
        out = (values < -1) | (values >= cells.n)
        if out.any():
            i, k = (int(a[0]) for a in np.nonzero(out))
            raise cells.bad(names[k], i, f"not a row of this file (0..{cells.n - 1})")
    if name == "q" and "reachable" in cols:  # a reachable grasp has its joint solution
        odd = cols["reachable"] & ~np.isfinite(values).all(axis=1)
        if odd.any():
            i = int(np.flatnonzero(odd)[0])
            k = int(np.flatnonzero(~np.isfinite(values[i]))[0])
            raise cells.bad(names[k], i, "a reachable grasp needs a finite joint value")
    return values


def _cell_names(spec: Column, header: list[str]) -> list[str]:
    """The cells a leading column is read from: its ``csv`` cells, or the file's q1, q2, ..."""
    if PER_JOINT in spec.csv[0]:
        return [h for h in header if _is_per_joint(h)]
    return list(spec.csv)


def _is_per_joint(name: str) -> bool:
    """Whether a header cell is a per-joint one (``q1``, ``q2``, ...)."""
    return name[:1] == "q" and name[1:].isdigit()


def _read_rows(path: Path) -> tuple[list[str], list[list[str]], list[int]]:
    """The header, the data rows and their line numbers of a CSV file (blank lines skipped).

    Raises:
        InputError: Missing, unreadable or empty file, a column named twice,
            a pose column missing, or a row with the wrong number of fields.
    """
    try:
        with path.open(newline="", encoding="utf-8-sig") as fh:
            reader = csv.reader(fh)
            rows: list[list[str]] = []
            lines: list[int] = []
            for row in reader:
                if any(cell.strip() for cell in row):
                    check_csv_cells(path, reader.line_num, rows[0] if rows else None, row)
                    rows.append(row)
                    lines.append(reader.line_num)
    except FileNotFoundError:
        raise InputError(f"not a run directory: {path} is missing", path=path) from None
    except UnicodeDecodeError as exc:
        raise InputError(
            f"{path}: not UTF-8 text ({exc.reason} at byte {exc.start})", path=path
        ) from None
    except (OSError, csv.Error) as exc:
        raise InputError(f"{path}: cannot read: {clip(str(exc))}", path=path) from None
    if not rows:
        raise InputError(f"{path}: empty file", path=path)
    header, body, lines = rows[0], rows[1:], lines[1:]
    if len(set(header)) != len(header):
        twice = next(h for h in header if header.count(h) > 1)
        raise InputError(
            f"{path}: the header names column {clip(twice)} twice", path=path, key=twice
        )
    missing = [c for c in COLUMNS["dq"].csv if c not in header]
    if missing:
        raise InputError(
            f"{path}: missing column(s) {', '.join(missing)}", path=path, key=missing[0]
        )
    for row, line in zip(body, lines, strict=True):
        if len(row) != len(header):
            raise InputError(
                f"{path}:{line}: {len(row)} fields, header has {len(header)}",
                path=path,
                row=line,
                value=len(row),
            )
    return header, body, lines


def check_csv_cells(path: Path, line: int, header: list[str] | None, row: list[str]) -> None:
    """Refuse a CSV row with a cell longer than :data:`~gcm_pipeline.bounds.MAX_CSV_CELL`.

    Raises:
        InputError: Names the line, the column and the cell's length
            (attributes ``path``, ``row``: the line, ``key``, ``value``: the length).
    """
    if max(map(len, row), default=0) <= MAX_CSV_CELL:
        return
    k = max(range(len(row)), key=lambda j: len(row[j]))
    name = clip(header[k], 40) if header is not None and k < len(header) else f"#{k + 1}"
    raise InputError(
        f"{path}:{line}: column {name}: a cell of {len(row[k]):,} characters; a CSV cell "
        f"holds at most {MAX_CSV_CELL} (gcm_pipeline.bounds.MAX_CSV_CELL)",
        path=path,
        row=line,
        key=name,
        value=len(row[k]),
    )


def _parse_column(values: Any) -> np.ndarray:
    """A further column read back: bool, int, float (empty = NaN) or, failing those, str."""
    text = np.array(values, dtype=str).reshape(-1)
    if text.size and all(v in ("true", "false") for v in text.tolist()):
        return text == "true"
    if text.size and all(re.fullmatch(r"-?[0-9]{1,18}", v) for v in text.tolist()):
        return text.astype(np.int64)
    floats = np.where(text == "", "nan", text)
    try:
        return floats.astype(float)
    except ValueError:
        return text
