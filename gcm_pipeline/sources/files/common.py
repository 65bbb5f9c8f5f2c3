"""What every grasp-file reader shares: the read grasps, size and rigidity checks, column names.

Sizes are checked before anything is allocated (:func:`check_count`,
:func:`check_bytes`); poses must be finite rigid transforms
(:func:`check_rigid`, :func:`check_poses`) within
:data:`~gcm_pipeline.bounds.MAX_GRASP_DISTANCE` of the file's origin
(:func:`check_positions`); a column a file carries gets a name that no
``grasps.csv`` or grasp-table column has (:func:`column_name`).
"""

from __future__ import annotations

import re
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from gcm_pipeline.bounds import MAX_GRASP_DISTANCE
from gcm_pipeline.errors import InputError, clip
from gcm_pipeline.rundir.grasps_csv import CSV_COLUMNS
from gcm_pipeline.table import COLUMNS

__all__ = [
    "ImportedGrasps",
    "as_poses",
    "check_bytes",
    "check_count",
    "check_poses",
    "check_positions",
    "check_rigid",
    "column_name",
    "score_column",
    "success_labels",
    "vector",
    "width_column",
]

#: Tolerance of the rigidity checks of imported matrices.
RIGID_TOL = 1e-4

#: Bytes of slack on top of what ``max_count`` grasps take (object, gripper, comments).
SLACK_BYTES = 1 << 20

#: Names a carried column must not have: the columns a run adds to the grasp table (the
#: registry :data:`gcm_pipeline.table.COLUMNS`: metrics, ``clearance``, ``patch``, ``q``,
#: ...) and the cells ``grasps.csv`` writes them as (``x``, ``qw``, ``v1``, ...; the
#: per-joint ``q1 .. q{nq}`` are matched by pattern).
RESERVED_COLUMNS = frozenset({*COLUMNS, *CSV_COLUMNS})


def check_count(path: Path, n: int, max_count: int) -> None:
    """Refuse a file of more than ``max_count`` grasps (``candidates.max_count``)."""
    if n > max_count:
        raise InputError(
            f"{path}: holds {n:,} grasps, more than candidates.max_count ({max_count:,}); "
            "raise candidates.max_count to read it",
            path=path,
        )


def check_bytes(path: Path, size: int, max_count: int, per_grasp: int, what: str) -> None:
    """Refuse a file whose grasps take more bytes than ``max_count`` of ``per_grasp`` bytes."""
    limit = max_count * per_grasp + SLACK_BYTES
    if size > limit:
        raise InputError(
            f"{path}: {what} take {size:,} bytes, more than {max_count:,} grasps "
            f"(candidates.max_count) need (at most {limit:,}); raise candidates.max_count "
            "to read it",
            path=path,
        )


@dataclass
class ImportedGrasps:
    """Grasps as a file stores them.

    Attributes:
        poses: (N, 4, 4) poses of the file's gripper frame [m].
        convention: The gripper-frame convention (``base`` or ``center``).
        columns: Per-candidate columns (N,) to carry through (``score``,
            ``width``, ``source_id``, ``segment``, ``object_id``).
        success: (N,) bool success labels, or None.
        depth: (N,) ``center`` convention: fingertip depth past the centre [m].
        gripper: The gripper named in the file, if any.
        selection: What :func:`~gcm_pipeline.sources.files.read_grasps` kept
            (:class:`~gcm_pipeline.sources.files.select.Selection`), once filtered.
    """

    poses: np.ndarray
    convention: str
    columns: dict[str, np.ndarray] = field(default_factory=dict)
    success: np.ndarray | None = None
    depth: np.ndarray | None = None
    gripper: str | None = None
    selection: Any = None

    def take(self, index: np.ndarray) -> ImportedGrasps:
        """The rows selected by an integer index or boolean mask."""
        return ImportedGrasps(
            poses=self.poses[index],
            convention=self.convention,
            columns={k: v[index] for k, v in self.columns.items()},
            success=None if self.success is None else self.success[index],
            depth=None if self.depth is None else self.depth[index],
            gripper=self.gripper,
        )


def check_positions(
    path: Path, positions: np.ndarray, where: Callable[[int], str] | None = None
) -> None:
    """Refuse a grasp farther than :data:`~gcm_pipeline.bounds.MAX_GRASP_DISTANCE` from the origin.

    A robot's world is metres across; a grasp 1e25 m away is a unit or
    export mistake, and further on it only breaks the manifold's geometry.

    Args:
        path: The file (for messages).
        positions: (N, 3) finite grasp positions as the file stores them [m].
        where: How a message names row ``i`` (default ``"<path>: grasp <i> (0-based)"``).

    Raises:
        InputError: Names the first such row and its position (attributes
            ``path``, ``row`` (0-based), ``value``: its distance [m]).
    """
    with np.errstate(over="ignore"):
        dist = np.linalg.norm(np.asarray(positions, dtype=float).reshape(-1, 3), axis=1)
    far = np.flatnonzero(~(dist <= MAX_GRASP_DISTANCE))
    if far.size:
        i = int(far[0])
        name = where(i) if where is not None else f"{path}: grasp {i} (0-based)"
        more = f" ({far.size:,} such grasps)" if far.size > 1 else ""
        xyz = ", ".join(f"{v:.6g}" for v in np.asarray(positions, dtype=float).reshape(-1, 3)[i])
        raise InputError(
            f"{name}: position ({xyz}) is {dist[i]:.3g} m from the file's origin, farther "
            f"than {MAX_GRASP_DISTANCE:g} m (gcm_pipeline.bounds.MAX_GRASP_DISTANCE): not a "
            f"grasp in a robot's world; are the units metres?{more}",
            path=path,
            row=i,
            value=float(dist[i]),
        )


def check_poses(path: Path, poses: np.ndarray, what: str) -> np.ndarray:
    """Return ``poses`` as float (N, 4, 4) or raise naming the first non-rigid row."""
    arr = np.asarray(poses)
    if arr.ndim != 3 or arr.shape[1:] != (4, 4):
        raise InputError(f"{path}: {what} must have shape (N, 4, 4), got {arr.shape}", path=path)
    if arr.dtype.kind not in "fiu":
        raise InputError(f"{path}: {what} must be real numbers, got dtype {arr.dtype}", path=path)
    arr = arr.astype(float)
    if len(arr) == 0:
        return arr
    rot = arr[:, :3, :3]
    with np.errstate(invalid="ignore"):
        err = np.abs(rot @ np.swapaxes(rot, 1, 2) - np.eye(3)).max(axis=(1, 2))
        err = np.maximum(err, np.abs(arr[:, 3] - [0.0, 0.0, 0.0, 1.0]).max(axis=1))
        det = np.linalg.det(np.nan_to_num(rot))
    bad = np.flatnonzero(~(np.isfinite(arr).all(axis=(1, 2)) & (err < RIGID_TOL) & (det > 0)))
    if bad.size:
        more = f" ({bad.size} bad rows in all)" if bad.size > 1 else ""
        raise InputError(
            f"{path}: {what}: grasp {int(bad[0])} (0-based) is not a rigid transform{more}",
            path=path,
        )
    check_positions(path, arr[:, :3, 3])
    return arr


def check_rigid(path: Path, poses: np.ndarray) -> None:
    """Raise naming the first row that is not a finite rigid transform."""
    if poses.shape[0] == 0:
        return
    finite = np.all(np.isfinite(poses), axis=(1, 2))
    rot = np.where(finite[:, None, None], poses[:, :3, :3], 0.0)
    with np.errstate(over="ignore", invalid="ignore"):  # huge entries: inf, not a warning
        ortho = np.abs(rot @ np.swapaxes(rot, 1, 2) - np.eye(3)).max(axis=(1, 2))
        det = np.linalg.det(rot)
        bottom = np.abs(poses[:, 3] - [0.0, 0.0, 0.0, 1.0]).max(axis=1)
    ok = finite & (ortho < RIGID_TOL) & (det > 0) & (bottom < RIGID_TOL)
    bad = np.flatnonzero(~ok)
    if bad.size == 0:
        return
    i = int(bad[0])
    if not finite[i]:
        why = "has non-finite entries"
    elif bottom[i] >= RIGID_TOL:
        why = f"has last row {poses[i, 3].tolist()}, expected [0, 0, 0, 1]"
    elif ortho[i] >= RIGID_TOL:
        why = f"has a non-orthonormal rotation (|R R^T - I| = {ortho[i]:.3g})"
    else:
        why = "has a reflection (det R < 0)"
    more = f" ({bad.size} bad rows in all)" if bad.size > 1 else ""
    raise InputError(
        f"{path}: grasp {i} (0-based row) is not a rigid transform: {why}{more}", path=path
    )


def as_poses(path: Path, arr: np.ndarray, what: str) -> np.ndarray:
    """``arr`` as float (N, 4, 4), or raise naming its shape or dtype."""
    if arr.ndim != 3 or arr.shape[1:] != (4, 4):
        raise InputError(f"{path}: {what} must have shape (N, 4, 4), got {arr.shape}", path=path)
    if arr.dtype.kind not in "fiu":
        raise InputError(f"{path}: {what} must be real numbers, got dtype {arr.dtype}", path=path)
    return np.asarray(arr, dtype=float)


def success_labels(
    path: Path,
    values: np.ndarray,
    n: int,
    what: str,
    where: Callable[[int], str] | None = None,
) -> np.ndarray:
    """(n,) bool success labels from 0/1 numbers, or raise naming ``what``.

    A label other than 0 or 1 (NaN, 0.5, 7, -1) is bad input (a broken export
    or a probability), not a grasp to keep or drop by a threshold: the message
    names the first such row (``where(i)``, default ``"<path>: <what>: grasp
    <i> (0-based)"``) and its value.
    """
    values = np.asarray(values).reshape(-1)
    if values.shape[0] != n:
        raise InputError(f"{path}: {what} has {values.shape[0]} values, expected {n}", path=path)
    if values.dtype.kind not in "biuf":
        raise InputError(f"{path}: {what} must be 0/1 values, got dtype {values.dtype}", path=path)
    values = values.astype(float)
    _refuse_first_bad(
        path,
        what,
        (values != 0.0) & (values != 1.0),
        where,
        lambda i: f"success label is {float(values[i])!r}",
        "every label must be 0 or 1",
        lambda i: float(values[i]),
    )
    return values == 1.0


def _refuse_first_bad(
    path: Path,
    key: str,
    bad: np.ndarray,
    where: Callable[[int], str] | None,
    problem: Callable[[int], str],
    rule: str,
    value: Callable[[int], Any] | None = None,
) -> None:
    """Raise naming the first row of mask ``bad`` (``where(i)``), its problem and the rule.

    ``where`` defaults to ``"<path>: <key>: grasp <i> (0-based)"``; more than
    one bad row is counted in the message.
    """
    rows = np.flatnonzero(bad)
    if not rows.size:
        return
    i = int(rows[0])
    name = where(i) if where is not None else f"{path}: {key}: grasp {i} (0-based)"
    more = f" ({rows.size:,} such grasps)" if rows.size > 1 else ""
    evidence = {} if value is None else {"value": value(i)}
    raise InputError(f"{name}: {problem(i)}; {rule}{more}", path=path, key=key, row=i, **evidence)


def _per_grasp(
    path: Path, values: Any, n: int, key: str, noun: str, not_numbers: str
) -> np.ndarray:
    """``values`` as (n,) float64, one ``noun`` per grasp, or one line naming the key."""
    try:
        arr = np.asarray(values, dtype=np.float64).reshape(-1)
    except (TypeError, ValueError):
        raise InputError(f"{path}: {key}: {not_numbers}", path=path, key=key) from None
    if arr.shape[0] != n:
        raise InputError(
            f"{path}: {key} has {arr.shape[0]:,} {noun}s for {n:,} grasps; one {noun} per grasp",
            path=path,
            key=key,
            value=arr.shape[0],
        )
    return arr


def score_column(
    path: Path,
    values: Any,
    n: int,
    key: str,
    where: Callable[[int], str] | None = None,
) -> np.ndarray:
    """A file's grasp quality as the ``score`` column: (n,) finite float64, or raise.

    A score of the wrong length, not a number, NaN or infinite is bad input
    (a broken export), never a grasp to drop silently: the message names the
    file, the key and the first bad row.

    Args:
        path: The file (for messages).
        values: The file's scores.
        n: How many grasps the file holds.
        key: Where the file stores them (``column 'score'``, ``grasps.confidences``).
        where: How a message names row ``i`` (default ``"<path>: <key>: grasp <i> (0-based)"``).

    Raises:
        InputError: Names the key and, for a non-finite score, the row (attributes
            ``path``, ``key``, ``row``, ``value``).
    """
    arr = _per_grasp(path, values, n, key, "score", "scores must be numbers")
    _refuse_first_bad(
        path,
        key,
        ~np.isfinite(arr),
        where,
        lambda i: f"score is {float(arr[i])}",
        "every score must be a finite number",
        lambda i: float(arr[i]),
    )
    return arr


def width_column(
    path: Path,
    values: Any,
    n: int,
    key: str,
    where: Callable[[int], str] | None = None,
) -> np.ndarray:
    """A file's finger opening as the ``width`` column: (n,) float64 [m], or raise.

    NaN is an unknown width (an empty CSV cell; the MoveIt export then closes
    the fingers fully). Text, a negative or an infinite width is bad input
    (it would become the export's finger posture): the message names the
    file, the key and the first bad row.

    Args:
        path: The file (for messages).
        values: The file's widths.
        n: How many grasps the file holds.
        key: Where the file stores them (``column 'width'``, ``gripper_openings[3]``).
        where: How a message names row ``i`` (default ``"<path>: <key>: grasp <i> (0-based)"``).

    Raises:
        InputError: Names the key and, for a bad width, the row (attributes
            ``path``, ``key``, ``row``, ``value``).
    """
    if np.asarray(values).dtype.kind in "USaMmV":  # text, times: never a width
        raise InputError(f"{path}: {key}: widths must be numbers [m]", path=path, key=key)
    arr = _per_grasp(path, values, n, key, "width", "widths must be numbers [m]")
    with np.errstate(invalid="ignore"):
        bad = np.isinf(arr) | (arr < 0.0)
    _refuse_first_bad(
        path,
        key,
        bad,
        where,
        lambda i: f"width {float(arr[i])!r}",
        "a finger opening is a finite number >= 0 [m] (empty or NaN: unknown)",
        lambda i: float(arr[i]),
    )
    return arr


def vector(path: Path, value: Any, n: int, what: str) -> np.ndarray:
    """``value`` as (n,) floats, or raise naming ``what``."""
    try:
        arr = np.asarray(value, dtype=float).reshape(-1)
    except (TypeError, ValueError):
        raise InputError(f"{path}: {what} must be numbers", path=path) from None
    if arr.shape[0] != n:
        raise InputError(f"{path}: {what} has {arr.shape[0]} values, expected {n}", path=path)
    return arr


def column_name(path: Path, raw: str, taken: set[str]) -> str:
    """A carried column's name: lower case, letters/digits/_ only, not reserved or taken."""
    name = re.sub(r"[^0-9a-z_]+", "_", raw.strip().lower()).strip("_") or "column"
    if name[0].isdigit():
        name = "c_" + name
    if name in RESERVED_COLUMNS or re.fullmatch(r"q[0-9]+", name):
        csv = name in CSV_COLUMNS or re.fullmatch(r"q[0-9]+", name)
        raise InputError(
            f"{path}: column {clip(raw)} has the name of a "
            f"{'grasps.csv' if csv else 'grasp-table'} column; rename it (e.g. input_{name})",
            path=path,
        )
    if name in taken:
        raise InputError(
            f"{path}: two columns are named {clip(name)}; rename one of them", path=path
        )
    taken.add(name)
    return name
