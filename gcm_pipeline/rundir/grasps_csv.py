"""``grasps.csv``: the grasp table as CSV, written and read back (checked).

One row per grasp, ranked rows first (rank 1 = best), then the unreachable
ones in table order. Columns, in this order: ``rank, origin, triangle, v1,
v2, v3, w1, w2, w3, x, y, z, qw, qx, qy, qz, reachable, reason, pos_err,
rot_err, manipulability, q1 .. q{nq}``, then any further metric columns, then
the per-candidate columns of the source
(:data:`~gcm_pipeline.table.CANDIDATE_COLUMNS`: ``score``, ``width``,
``source_id``, ...; integers as integers, strings quoted when needed). Poses
are the grasp frame in the world (quaternion with ``qw >= 0``). Floats are
written with :func:`repr` (they round-trip exactly); NaN is an empty cell;
booleans are ``true`` / ``false``.
"""

from __future__ import annotations

import csv
import re
from pathlib import Path
from typing import Any

import numpy as np

from gcm_pipeline.bounds import MAX_CSV_CELL
from gcm_pipeline.errors import InputError, clip
from gcm_pipeline.geometry.dualquat import dq_from_pos_quat, dq_to_pos_quat
from gcm_pipeline.table import CANDIDATE_COLUMNS, GraspTable

__all__ = [
    "CSV_COLUMNS",
    "check_csv_cells",
    "format_floats",
    "read_grasps_csv",
    "write_grasps_csv",
]

#: Fixed leading columns of ``grasps.csv`` (then ``q1 .. q{nq}`` and extra metrics).
CSV_COLUMNS = (
    "rank",
    "origin",
    "triangle",
    "v1",
    "v2",
    "v3",
    "w1",
    "w2",
    "w3",
    "x",
    "y",
    "z",
    "qw",
    "qx",
    "qy",
    "qz",
    "reachable",
    "reason",
    "pos_err",
    "rot_err",
    "manipulability",
)

#: Table columns that grasps.csv writes under other names (or derives).
_KNOWN = {"dq", "rank", "origin", "triangle", "vertices", "weights", "reachable", "reason"}
_KNOWN |= {"q", "pos_err", "rot_err", "manipulability"}


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


def _ints(values: np.ndarray) -> list[str]:
    return [str(v) for v in np.asarray(values, dtype=np.int64).tolist()]


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
        if name in _KNOWN or col.ndim != 1:
            continue
        if np.issubdtype(col.dtype, np.number) or col.dtype == bool or col.dtype.kind in "US":
            extra.append(name)
    return [n for n in extra if n not in CANDIDATE_COLUMNS] + [
        n for n in extra if n in CANDIDATE_COLUMNS
    ]


def _cells(values: np.ndarray) -> list[str]:
    """CSV cells of a 1-D column by dtype: bool, int, float (repr) or quoted text."""
    kind = values.dtype.kind
    if kind == "b":
        return ["true" if b else "false" for b in values.tolist()]
    if kind in "iu":
        return _ints(values)
    if kind in "US":
        return [_quote(str(v)) for v in values.tolist()]
    return format_floats(values)


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
    g = grasps.take(order)
    n = len(g)
    empty = [""] * n
    csv_row = np.empty(n, dtype=np.int64)
    csv_row[order] = np.arange(n)
    pos, quat = dq_to_pos_quat(g["dq"])
    quat = np.where(quat[:, :1] < 0, -quat, quat)  # same rotation, qw >= 0

    def col(name: str, fmt: Any) -> list[str]:
        return fmt(g[name]) if name in g else empty

    def bools(v: np.ndarray) -> list[str]:
        return ["true" if b else "false" for b in np.asarray(v, dtype=bool).tolist()]

    def strs(v: np.ndarray) -> list[str]:
        return [_quote(str(s)) for s in np.asarray(v).tolist()]

    cols: list[list[str]] = [col("rank", _ints), col("origin", strs), col("triangle", _ints)]
    if "vertices" in g:  # table rows -> the data rows of this file that hold them
        vert = np.asarray(g["vertices"], dtype=np.int64).reshape(n, 3)
        ok = (vert >= 0) & (vert < n)
        vert = np.where(ok, csv_row[np.where(ok, vert, 0)], vert)
    for k in range(3):
        cols.append(_ints(vert[:, k]) if "vertices" in g else empty)
    for k in range(3):
        cols.append(format_floats(g["weights"][:, k]) if "weights" in g else empty)
    cols += [format_floats(pos[:, k]) for k in range(3)]
    cols += [format_floats(quat[:, k]) for k in range(4)]
    cols += [col("reachable", bools), col("reason", strs)]
    cols += [col(name, format_floats) for name in ("pos_err", "rot_err", "manipulability")]
    header = list(CSV_COLUMNS)
    if "q" in g:
        q = np.asarray(g["q"], dtype=float)
        q = q.reshape(n, q.shape[1] if q.ndim == 2 else 1)
        header += [f"q{j + 1}" for j in range(q.shape[1])]
        cols += [format_floats(q[:, j]) for j in range(q.shape[1])]
    for name in _extra_columns(g):
        header.append(name)
        cols.append(_cells(np.asarray(g[name])))
    with Path(path).open("w", newline="", encoding="utf-8") as fh:
        fh.write(",".join(header) + "\n")
        fh.writelines(",".join(row) + "\n" for row in zip(*cols, strict=True))
    return order


def read_grasps_csv(path: str | Path) -> GraspTable:
    """Read ``grasps.csv`` back into a grasp table (``dq`` rebuilt from x..qz).

    Rows stay in file order (ranked first), so ``vertices`` (from ``v1, v2,
    v3``) index the table's rows. Columns: ``dq``, ``rank``, ``origin``,
    ``triangle``, ``vertices``, ``weights``, ``reachable``, ``reason``,
    ``pos_err``, ``rot_err``, ``manipulability``, ``q`` and the further
    columns, as far as the file has them.

    The file is checked as it is read: unit quaternions, finite positions,
    ``true``/``false`` switches, integer ids, ``v1..v3`` that name rows of the
    file; a UTF-8 byte order mark and blank lines are ignored.

    Raises:
        InputError: Missing file or columns, or a value that does not parse
            (names the line and column).
    """
    path = Path(path)
    header, body, lines = _read_rows(path)
    n = len(body)
    # Python strings: a fixed-width array is as wide as the longest cell in every cell
    cells = np.empty((n, len(header)), dtype=object)
    if body:
        cells[:] = body
    raw = {name: cells[:, k] for k, name in enumerate(header)}

    def bad(name: str, i: int, what: str) -> InputError:
        return InputError(f"{path}:{lines[i]}: column {name!r}: {what}: {clip(str(raw[name][i]))}")

    def floats(name: str) -> np.ndarray:
        col = np.where(raw[name] == "", "nan", raw[name])
        try:
            return col.astype(float)
        except ValueError:
            for i, text in enumerate(col.tolist()):
                try:
                    float(text)
                except ValueError:
                    raise bad(name, i, "not a number") from None
            raise  # pragma: no cover

    def ints(name: str) -> np.ndarray:
        col = raw[name]
        ok = np.array([re.fullmatch(r"-?[0-9]{1,18}", t) is not None for t in col.tolist()])
        if n and not ok.all():
            raise bad(name, int(np.flatnonzero(~ok)[0]), "not an integer")
        return col.astype(np.int64).reshape(n)

    pos = np.column_stack([floats(c) for c in ("x", "y", "z")]).reshape(n, 3)
    quat = np.column_stack([floats(c) for c in ("qw", "qx", "qy", "qz")]).reshape(n, 4)
    broken = ~np.isfinite(pos).all(axis=1) | ~np.isfinite(quat).all(axis=1)
    with np.errstate(invalid="ignore"):
        broken |= np.abs(np.linalg.norm(quat, axis=1) - 1.0) > 1e-6
    if broken.any():
        i = int(np.flatnonzero(broken)[0])
        raise InputError(
            f"{path}:{lines[i]}: not a pose: x,y,z must be finite and qw,qx,qy,qz a unit "
            f"quaternion, got {pos[i].tolist()} and {quat[i].tolist()}"
        )
    cols: dict[str, Any] = {"dq": dq_from_pos_quat(pos, quat)}
    if "rank" in raw:
        cols["rank"] = ints("rank")
        if (cols["rank"] < 0).any():
            raise bad("rank", int(np.flatnonzero(cols["rank"] < 0)[0]), "negative")
    if "origin" in raw:
        cols["origin"] = raw["origin"].astype(str)
        odd = ~np.isin(cols["origin"], ("candidate", "interpolated", ""))
        if odd.any():
            raise bad("origin", int(np.flatnonzero(odd)[0]), "not candidate or interpolated")
    if "triangle" in raw:
        cols["triangle"] = ints("triangle")
    if all(c in raw for c in ("v1", "v2", "v3")):
        vert = np.column_stack([ints(c) for c in ("v1", "v2", "v3")]).reshape(n, 3)
        out = (vert < -1) | (vert >= n)
        if out.any():
            i, k = (int(a[0]) for a in np.nonzero(out))
            raise bad(f"v{k + 1}", i, f"not a row of this file (0..{n - 1})")
        cols["vertices"] = vert
    if all(c in raw for c in ("w1", "w2", "w3")):
        cols["weights"] = np.column_stack([floats(c) for c in ("w1", "w2", "w3")]).reshape(n, 3)
    if "reachable" in raw:
        cols["reachable"] = _switches(path, raw["reachable"], "reachable", lines)
    if "reason" in raw:
        cols["reason"] = raw["reason"].astype(str)
    for name in ("pos_err", "rot_err", "manipulability"):
        if name in raw:
            cols[name] = floats(name)
    qnames = [h for h in header if h[:1] == "q" and h[1:].isdigit()]
    if qnames:
        cols["q"] = np.column_stack([floats(c) for c in qnames]).reshape(n, len(qnames))
        if "reachable" in cols:  # a reachable grasp has its joint solution
            odd = cols["reachable"] & ~np.isfinite(cols["q"]).all(axis=1)
            if odd.any():
                i = int(np.flatnonzero(odd)[0])
                k = int(np.flatnonzero(~np.isfinite(cols["q"][i]))[0])
                raise bad(qnames[k], i, "a reachable grasp needs a finite joint value")
    for name in header:
        if name in CSV_COLUMNS or name in qnames or name in cols:
            continue
        cols[name] = _parse_column(raw[name])
    return GraspTable(cols)


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
        raise InputError(f"not a run directory: {path} is missing") from None
    except UnicodeDecodeError as exc:
        raise InputError(f"{path}: not UTF-8 text ({exc.reason} at byte {exc.start})") from None
    except (OSError, csv.Error) as exc:
        raise InputError(f"{path}: cannot read: {clip(str(exc))}") from None
    if not rows:
        raise InputError(f"{path}: empty file")
    header, body, lines = rows[0], rows[1:], lines[1:]
    if len(set(header)) != len(header):
        twice = next(h for h in header if header.count(h) > 1)
        raise InputError(f"{path}: the header names column {clip(twice)} twice")
    missing = [c for c in ("x", "y", "z", "qw", "qx", "qy", "qz") if c not in header]
    if missing:
        raise InputError(f"{path}: missing column(s) {', '.join(missing)}")
    for row, line in zip(body, lines, strict=True):
        if len(row) != len(header):
            raise InputError(f"{path}:{line}: {len(row)} fields, header has {len(header)}")
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


def _switches(path: Path, text: np.ndarray, name: str, lines: list[int]) -> np.ndarray:
    odd = ~np.isin(text, ("true", "false"))
    if odd.any():
        i = int(np.flatnonzero(odd)[0])
        raise InputError(
            f"{path}:{lines[i]}: column {name!r}: not true or false: {clip(str(text[i]))}"
        )
    return np.asarray(text == "true", dtype=bool)


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
