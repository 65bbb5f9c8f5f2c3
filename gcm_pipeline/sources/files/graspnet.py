"""``format: graspnet``: GraspNet-1Billion / AnyGrasp ``GraspGroup`` arrays.

An ``.npy``, or the only (or ``grasp_group_array``) array of an ``.npz``: rows
of 17 values ``[score, width, height, depth, R (9, row-major), t (3),
object_id]`` [m]. Source: graspnetAPI's ``grasp.py`` (``GRASP_ARRAY_LEN =
17`` and the accessors ``rotation_matrices = rows[:, 4:13].reshape(-1, 3,
3)``, ``translations = rows[:, 13:16]``).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from gcm_pipeline.bounds import DEFAULT_MAX_CANDIDATES
from gcm_pipeline.errors import InputError, clip
from gcm_pipeline.rundir.arrays import npy_header
from gcm_pipeline.sources.files.common import (
    ImportedGrasps,
    check_count,
    check_poses,
    check_positions,
    score_column,
    width_column,
)
from gcm_pipeline.sources.files.pickled import read_npz_members
from gcm_pipeline.sources.files.sniff import check_format, sniff

__all__ = ["GRASPNET_ROW", "read_graspnet"]

#: Values per grasp row (graspnetAPI's ``GRASP_ARRAY_LEN``).
GRASPNET_ROW = 17


def read_graspnet(path: str | Path, *, max_count: int = DEFAULT_MAX_CANDIDATES) -> ImportedGrasps:
    """Read GraspNet-1Billion / AnyGrasp grasp rows (``GraspGroup`` arrays).

    Args:
        path: The ``.npy`` (or ``.npz``) file.
        max_count: Most grasps the file may hold (``candidates.max_count``),
            checked from the array's header before it is read.

    Returns:
        Grasp-centre poses (``center`` convention) with ``score``, ``width``
        [m], ``object_id`` and ``source_id`` (row in the file); ``depth`` [m].

    Raises:
        InputError: Not a (N, 17) real array, non-rigid rotation, bad values
            (a negative width, an ``object_id`` that is not a whole number, a
            fingertip farther than ``MAX_GRASP_DISTANCE`` from the origin).
    """
    path = Path(path)
    check_format(path, "graspnet")
    kind = getattr(sniff(path), "kind", None)  # the suffix when the start says nothing
    if kind == "zip" or (kind is None and path.suffix.lower() == ".npz"):
        arrays = read_npz_members(path, max_count)
        names: list[str] = [k for k in ("grasp_group_array", "grasps", "preds") if k in arrays]
        if not names and len(arrays) == 1:
            names = list(arrays)
        if not names:
            raise InputError(
                f"{path}: expected one array of GraspNet rows (N, {GRASPNET_ROW}) or "
                f"'grasp_group_array'; arrays: {', '.join(arrays) or 'none'}",
                path=path,
            )
        rows = arrays[names[0]]
    else:
        rows = _read_graspnet_npy(path, max_count)
    rows = np.asarray(rows)
    _check_graspnet_shape(path, rows.shape, rows.dtype)
    check_count(path, len(rows), max_count)
    rows = rows.astype(float)
    score_column(path, rows[:, 0], len(rows), "column 0 (score)")
    bad = np.flatnonzero(~np.isfinite(rows).all(axis=1))
    if bad.size:
        raise InputError(f"{path}: row {int(bad[0])} (0-based) has non-finite values", path=path)
    bad = np.flatnonzero((np.abs(rows[:, 16]) >= 2.0**53) | (rows[:, 16] != np.rint(rows[:, 16])))
    if bad.size:
        raise InputError(
            f"{path}: row {int(bad[0])} (0-based): object_id {rows[bad[0], 16]:g} is not an "
            "integer id",
            path=path,
            row=int(bad[0]),
            value=float(rows[bad[0], 16]),
        )
    n = len(rows)
    width = width_column(
        path, rows[:, 1], n, "column 1 (width)", where=lambda i: f"{path}: row {i} (0-based)"
    )
    poses = np.zeros((n, 4, 4))
    poses[:, :3, :3] = rows[:, 4:13].reshape(n, 3, 3)
    poses[:, :3, 3] = rows[:, 13:16]
    poses[:, 3, 3] = 1.0
    poses = check_poses(path, poses, "rotation/translation")
    # the fingertips, `depth` past the centre along the approach (x): as bounded as the centre
    tips = rows[:, 13:16] + rows[:, 3:4] * poses[:, :3, 0]
    check_positions(path, tips, lambda i: f"{path}: row {i} (0-based): fingertips")
    columns = {
        "score": rows[:, 0].copy(),
        "width": width,
        "object_id": np.rint(rows[:, 16]).astype(np.int64),
        "source_id": np.arange(n, dtype=np.int64),
    }
    return ImportedGrasps(poses, "center", columns, depth=rows[:, 3].copy())


def _check_graspnet_shape(path: Path, shape: tuple[int, ...], dtype: np.dtype[Any]) -> None:
    if len(shape) != 2 or shape[1] != GRASPNET_ROW or dtype.kind not in "fiu":
        raise InputError(
            f"{path}: expected GraspNet rows (N, {GRASPNET_ROW}) = [score, width, height, "
            f"depth, R (9), t (3), object_id], got shape {shape} dtype {dtype}",
            path=path,
        )


def _read_graspnet_npy(path: Path, max_count: int) -> np.ndarray:
    """The rows of a ``.npy`` file, its header checked before the data is read."""
    try:
        with path.open("rb") as fh:
            shape, dtype = npy_header(path, fh, "the array", path.stat().st_size)
            _check_graspnet_shape(path, shape, dtype)
            check_count(path, shape[0], max_count)
            fh.seek(0)
            return np.lib.format.read_array(fh, allow_pickle=False)
    except OSError as exc:
        raise InputError(f"{path}: cannot read: {exc.strerror or exc}", path=path) from None
    except ValueError as exc:
        raise InputError(
            f"{path}: not a readable .npy array: {clip(str(exc))}", path=path
        ) from None
