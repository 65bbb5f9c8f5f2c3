"""``format: npz``: poses, ``success`` labels and carried columns of a NumPy ``.npz`` archive."""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any

import numpy as np

from gcm_pipeline.errors import InputError, clip
from gcm_pipeline.rundir.arrays import read_npz as read_npz_arrays
from gcm_pipeline.sources.files.common import (
    as_poses,
    check_count,
    column_name,
    score_column,
    success_labels,
    width_column,
)

__all__ = ["read_npz"]

log = logging.getLogger(__name__)

#: Bytes per grasp an .npz may hold (a 128-byte pose and some columns).
_NPZ_BYTES_PER_GRASP = 256


def read_npz(
    path: Path, max_count: int
) -> tuple[np.ndarray, np.ndarray | None, dict[str, np.ndarray]]:
    """Poses, ``success`` labels (or None) and carried columns of an ``.npz`` grasp file.

    The poses are array ``transforms`` (or ``poses``, or the only 3-D array);
    other 1-D arrays of one number or string per grasp are carried as columns.
    An array ``score`` is the grasps' quality: one finite number per grasp
    (:func:`~gcm_pipeline.sources.files.common.score_column`); an array
    ``width`` the finger opening, one number per grasp
    (:func:`~gcm_pipeline.sources.files.common.width_column`).
    """
    arrays = read_npz_arrays(
        path,
        max_bytes=max_count * _NPZ_BYTES_PER_GRASP,
        keep=lambda name, shape, dtype: len(shape) in (1, 3),
    )
    poses_name = _npz_poses_name(path, {k: (v.shape, v.dtype) for k, v in arrays.items()})
    poses = as_poses(path, arrays.pop(poses_name), f"array {poses_name!r}")
    check_count(path, len(poses), max_count)
    success = arrays.pop("success", None)
    if success is not None:
        success = success_labels(path, success, poses.shape[0], "array 'success'")
    columns: dict[str, np.ndarray] = {}
    taken: set[str] = {"source_id", "success"}
    for name, values in arrays.items():
        if name == "score":  # the file's quality: validated, never skipped
            taken.add("score")
            columns["score"] = score_column(path, values, len(poses), "array 'score'")
            continue
        if name == "width":  # the finger opening [m]: one number per grasp
            taken.add("width")
            columns["width"] = width_column(path, values, len(poses), "array 'width'")
            continue
        if values.ndim != 1 or len(values) != len(poses) or values.dtype.kind not in "biufU":
            log.info(
                "%s: array %r %s is not one value per grasp; not read", path, name, values.shape
            )
            continue
        columns[column_name(path, name, taken)] = values
    return poses, success, columns


def _npz_poses_name(path: Path, headers: dict[str, tuple[tuple[int, ...], Any]]) -> str:
    for name in ("transforms", "poses"):
        if name in headers:
            return name
    three_d = [k for k, (shape, _) in headers.items() if len(shape) == 3]
    if len(three_d) != 1:
        names = ", ".join(clip(k, 40) for k in list(headers)[:20]) or "none"
        raise InputError(
            f"{path}: expected an array 'transforms' (N, 4, 4); arrays: {names}", path=path
        )
    return three_d[0]
