"""A run directory's files, written together and read back for ``gcm show`` / ``gcm plot``.

A run directory holds (see DESIGN.md, *Run directory*):

- ``grasps.csv`` (:mod:`gcm_pipeline.rundir.grasps_csv`);
- ``summary.json``: counts, timings [s], the ranking's top grasps, the
  resolved config and package versions;
- ``manifold.npz``, ``configurations.npz`` and, with ``ik.solutions`` > 1,
  ``solutions.npz`` (:mod:`gcm_pipeline.rundir.arrays`);
- ``config.yaml``: the resolved config;
- optional ``scene.html`` and ``*.png`` from the publish stage;
- ``.gcm.json``, the marker (:mod:`gcm_pipeline.rundir.transaction`, which
  writes the directory atomically).
"""

from __future__ import annotations

import json
import math
import platform
from collections.abc import Mapping
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np
import yaml

from gcm_pipeline.errors import InputError, clip
from gcm_pipeline.manifold.build import Manifold
from gcm_pipeline.rundir.arrays import (
    manifold_vertex_rows,
    read_configurations,
    read_manifold,
    write_configurations,
    write_manifold,
    write_solutions,
)
from gcm_pipeline.rundir.grasps_csv import read_grasps_csv, write_grasps_csv
from gcm_pipeline.rundir.transaction import is_project_dir
from gcm_pipeline.table import GraspTable

__all__ = [
    "RUN_FILES",
    "RunData",
    "json_clean",
    "objects_hint",
    "read_run",
    "read_summary",
    "versions",
    "write_config",
    "write_run_files",
    "write_summary",
]

RUN_FILES = ("grasps.csv", "summary.json", "manifold.npz", "config.yaml")


#: Most bytes of a run's summary.json that are read.
_MAX_SUMMARY_BYTES = 64 << 20


def write_run_files(
    out_dir: str | Path, grasps: GraspTable, manifold: Manifold, config: Mapping[str, Any]
) -> None:
    """Write ``grasps.csv``, ``manifold.npz`` (vertex ids = csv rows) and ``config.yaml``."""
    out = Path(out_dir)
    order = write_grasps_csv(grasps, out / "grasps.csv")
    csv_row = np.empty(len(order), dtype=np.int64)
    csv_row[order] = np.arange(len(order))
    write_manifold(manifold, out / "manifold.npz", csv_rows=csv_row[: len(manifold.chart)])
    write_configurations(grasps, out / "configurations.npz", order)
    if "solutions" in grasps:
        write_solutions(grasps, out / "solutions.npz", order)
    write_config(config, out / "config.yaml")


# ------------------------------------------------------------ json / yaml


def json_clean(value: Any) -> Any:
    """NumPy scalars/arrays to Python, NaN/inf to None, paths to str."""
    if isinstance(value, Mapping):
        return {str(k): json_clean(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [json_clean(v) for v in value]
    if isinstance(value, np.ndarray):
        return json_clean(value.tolist())
    if isinstance(value, np.generic):
        return json_clean(value.item())
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if isinstance(value, Path):
        return str(value)
    return value


def versions() -> dict[str, str]:
    """Versions of Python and the main packages, for ``summary.json``."""
    out = {"python": platform.python_version()}
    for name, module in (
        ("gcm_pipeline", "gcm_pipeline"),
        ("numpy", "numpy"),
        ("scipy", "scipy"),
        ("pinocchio", "pinocchio"),
        ("pydantic", "pydantic"),
    ):
        try:
            out[name] = str(__import__(module).__version__)
        except (ImportError, AttributeError):
            continue
    return out


def write_summary(summary: Mapping[str, Any], path: str | Path) -> None:
    """Write ``summary.json`` (NaN becomes null; keys in the given order)."""
    text = json.dumps(json_clean(summary), indent=2, allow_nan=False)
    Path(path).write_text(text + "\n", encoding="utf-8")


def write_config(config: Mapping[str, Any], path: str | Path) -> None:
    """Write the resolved config as YAML (section order kept)."""
    text = yaml.safe_dump(json_clean(config), sort_keys=False, default_flow_style=None)
    Path(path).write_text(text, encoding="utf-8")


# ------------------------------------------------------------ read_run


class RunData(NamedTuple):
    """A run directory read back by :func:`read_run`.

    Attributes:
        grasps: The grasp table: candidates first, in manifold vertex order,
            then the other rows in file order (ranked first).
        manifold: The manifold (triangles index the candidate rows).
        summary: ``summary.json`` as a dict.
        run_dir: The run directory.
    """

    grasps: GraspTable
    manifold: Manifold
    summary: dict[str, Any]
    run_dir: Path


def objects_hint(run_dir: Path) -> str:
    """What the folder is instead, for a 'not a run directory' message ('' if nothing known).

    A ``target: all`` folder: its runs per object. A study directory (marker
    kind ``study``): where its best placement's run is (``best/``), or that
    it has none yet, and ``gcm show`` for the study itself.
    """
    if is_project_dir(run_dir, "study"):
        best = run_dir / "best"
        if is_project_dir(best, "run"):
            return (
                f"; it is a study directory: its best placement's run is {best} "
                f"(gcm show {run_dir} summarises the study)"
            )
        return (
            f"; it is a study directory and has no best/ (the best placement's run) yet: the "
            f"study did not finish or ran with --no-best (gcm show {run_dir} summarises it)"
        )
    runs = sorted(p.parent.name for p in (run_dir / "objects").glob("*/grasps.csv"))
    return f"; it holds one run per object in objects/: {', '.join(runs)}" if runs else ""


def read_run(run_dir: str | Path) -> RunData:
    """Read a run directory written by ``gcm run`` / :meth:`Pipeline.run`.

    Args:
        run_dir: The run directory.

    Returns:
        The grasp table (``dq`` rebuilt from x..qz), the manifold and the
        summary. The table's rows are ordered as in the run: the candidates
        first, in manifold vertex order (so the manifold's triangles and the
        ``vertices`` column index them), then the other rows in file order
        (ranked first).

    Raises:
        InputError: Not a run directory, or a file in it cannot be read or
            does not match the others (names the file and what is wrong).
    """
    run_dir = Path(run_dir)
    if not run_dir.is_dir():
        if run_dir.exists():
            raise InputError(f"not a run directory: {run_dir} is a file (give its folder)")
        raise InputError(f"run directory not found: {run_dir}")
    missing = [
        f for f in ("grasps.csv", "summary.json", "manifold.npz") if not (run_dir / f).is_file()
    ]
    if is_project_dir(run_dir, "study"):  # its files are not what it lacks
        raise InputError(f"not a run directory: {run_dir}{objects_hint(run_dir)}", path=run_dir)
    if missing:
        hint = objects_hint(run_dir)
        raise InputError(f"not a run directory: {run_dir} lacks {', '.join(missing)}{hint}")
    summary = read_summary(run_dir / "summary.json")
    grasps = read_grasps_csv(run_dir / "grasps.csv")
    if "q" in grasps and np.ndim(grasps["q"]) == 2:  # the approach and retreat of each row
        nq = np.shape(grasps["q"])[1]
        extra = read_configurations(run_dir / "configurations.npz", len(grasps), nq)
        grasps = grasps.with_columns(**extra) if extra else grasps
    manifold = read_manifold(run_dir / "manifold.npz", n_rows=len(grasps))
    vertex_rows = manifold_vertex_rows(run_dir / "manifold.npz", len(manifold.chart))
    n = len(grasps)
    is_vertex = np.zeros(n, dtype=bool)
    is_vertex[vertex_rows] = True  # unique rows of the file (read_manifold checks them)
    if "vertices" in grasps and n:
        used = np.asarray(grasps["vertices"]).reshape(-1)
        used = used[used >= 0]
        named = np.zeros(max(n, int(used.max(initial=-1)) + 1), dtype=bool)
        named[used] = True
        named[:n] &= ~is_vertex
        stray = np.flatnonzero(named)
        if stray.size:
            raise InputError(
                f"{run_dir / 'grasps.csv'}: v1..v3 name row {int(stray[0])}, which is not a "
                "candidate of manifold.npz"
            )
    grasps = GraspTable(_candidates_first(grasps, vertex_rows, is_vertex))
    if "vertices" in grasps:  # rows of the file -> rows of the reordered table
        new_row = np.empty(n, dtype=np.int64)
        new_row[vertex_rows] = np.arange(len(vertex_rows))
        new_row[~is_vertex] = np.arange(len(vertex_rows), n)
        vert = np.asarray(grasps["vertices"])
        grasps = grasps.with_columns(vertices=np.where(vert >= 0, new_row[np.maximum(vert, 0)], -1))
    return RunData(grasps, manifold, summary, run_dir)


#: Most candidate rows moved in place by :func:`_candidates_first` (one copy per segment between
#: two of them); a table with more is reordered by a copy.
_MOVES_IN_PLACE = 4096


def _candidates_first(
    grasps: GraspTable, rows: np.ndarray, is_row: np.ndarray
) -> dict[str, np.ndarray]:
    """The columns of ``grasps`` with ``rows`` first (in that order), then the others in order.

    The same as ``grasps.take(np.concatenate([rows, np.flatnonzero(~is_row)]))``.
    A column that holds its memory alone (as the readers return them) is
    reordered in place: the rows between two of ``rows`` are moved as one block
    towards the end, so a big table is not copied (a fresh copy of a million
    rows costs more in page faults than in copying). Others are copied.
    """
    k = len(rows)
    cols = dict(zip(grasps.columns, (grasps[c] for c in grasps.columns), strict=True))
    if k == 0 or np.array_equal(rows, np.arange(k)):
        return cols
    perm: np.ndarray | None = None
    owners = [_owner(a) for a in cols.values()]
    shared = {id(o) for o in owners if sum(o is p for p in owners) > 1}
    ends = np.sort(rows)
    for (name, values), owner in zip(cols.items(), owners, strict=True):
        if k <= _MOVES_IN_PLACE and id(owner) not in shared and _writable(values):
            _move_first(values, rows, ends)
            values.setflags(write=False)
        else:
            perm = np.concatenate([rows, np.flatnonzero(~is_row)]) if perm is None else perm
            cols[name] = values[perm]
    return cols


def _owner(values: np.ndarray) -> object:
    """The object that holds an array's memory (its last base)."""
    base: object = values
    while isinstance(base, np.ndarray) and base.base is not None:
        base = base.base
    return base


def _writable(values: np.ndarray) -> bool:
    """Whether a C-contiguous array with rows of bytes can be written in place.

    Not an array of Python objects: its rows are references, not bytes to move.
    """
    if values.dtype.hasobject or values.ndim == 0 or values.itemsize == 0:
        return False
    if not values.flags.c_contiguous:
        return False
    try:
        values.setflags(write=True)
    except ValueError:  # memory of another library (Arrow), read-only
        return False
    return True


def _move_first(values: np.ndarray, rows: np.ndarray, ends: np.ndarray) -> None:
    """In place: ``rows`` first, then the other rows in order (``ends``: ``rows`` sorted)."""
    head = values[rows].copy()
    size = values.strides[0]
    flat = values.reshape(-1).view(np.uint8)
    k = len(ends)
    # the rows between ends[j - 1] and ends[j] move k - j rows down; from the last block
    # back, each lands where rows already moved or candidates were (1-D copies may overlap)
    for j in range(k - 1, -1, -1):
        lo = int(ends[j - 1]) + 1 if j else 0
        hi, shift = int(ends[j]), k - j
        if hi > lo:
            flat[(lo + shift) * size : (hi + shift) * size] = flat[lo * size : hi * size]
    values[:k] = head


def read_summary(path: str | Path) -> dict[str, Any]:
    """Read and check a run's ``summary.json``.

    ``counts`` (when present) maps names to counts or to ``{reason: count}``
    breakdowns; ``ranking`` (when present) has a text ``metric`` and a list
    ``top``.

    Raises:
        InputError: Unreadable, not JSON, not an object, or a part of the
            wrong type (names it).
    """
    path = Path(path)
    try:
        with path.open("rb") as fh:
            data = fh.read(_MAX_SUMMARY_BYTES + 1)
    except OSError as exc:
        raise InputError(f"{path}: cannot read: {exc.strerror or exc}", path=path) from None
    if len(data) > _MAX_SUMMARY_BYTES:
        raise InputError(
            f"{path}: larger than {_MAX_SUMMARY_BYTES >> 20} MiB; not a summary", path=path
        )
    try:
        summary = json.loads(data.decode("utf-8"))
    except (ValueError, RecursionError) as exc:
        raise InputError(f"{path}: not valid JSON: {clip(str(exc))}", path=path) from None
    if not isinstance(summary, dict):
        raise InputError(f"{path}: expected a JSON object, got {type(summary).__name__}", path=path)
    counts = summary.get("counts", {})
    if not isinstance(counts, dict):
        raise InputError(
            f"{path}: 'counts' must be an object, got {type(counts).__name__}", path=path
        )
    for key, value in counts.items():
        ok = (isinstance(value, int) and not isinstance(value, bool)) or (
            isinstance(value, dict)
            and all(isinstance(v, int) and not isinstance(v, bool) for v in value.values())
        )
        if not ok:
            raise InputError(
                f"{path}: counts.{str(key)[:60]} must be a count, got {clip(value)}", path=path
            )
    ranking = summary.get("ranking", {})
    if not isinstance(ranking, dict):
        raise InputError(
            f"{path}: 'ranking' must be an object, got {type(ranking).__name__}", path=path
        )
    if not isinstance(ranking.get("metric", ""), str):
        raise InputError(
            f"{path}: ranking.metric must be a text, got {clip(ranking['metric'])}", path=path
        )
    if not isinstance(ranking.get("top", []), list):
        raise InputError(f"{path}: ranking.top must be a list", path=path)
    return summary
