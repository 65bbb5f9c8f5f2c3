"""``format: contact_graspnet``: Contact-GraspNet's ``predictions_*.npz``.

Dicts keyed by segment id (stored as pickled 0-d object arrays, read by
:mod:`~gcm_pipeline.sources.files.pickled`): ``pred_grasps_cam`` (M, 4, 4)
gripper base poses in the camera frame (OpenCV: x right, y down, z forward),
``scores`` (M,), ``contact_pts`` (M, 3), optional ``gripper_openings`` (M,)
[m]; plain arrays (no dict) are one segment (-1). Source: Contact-GraspNet's
``inference.py`` (``np.savez`` of ``pred_grasps_cam``, ``scores``,
``contact_pts``; later versions add ``gripper_openings``).

The contact points become the per-candidate columns ``contact_x``,
``contact_y``, ``contact_z`` (:data:`CONTACT_COLUMNS`), in the camera frame
here; the ``candidates`` step moves them with the poses (``camera_pose``).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from gcm_pipeline.bounds import DEFAULT_MAX_CANDIDATES
from gcm_pipeline.errors import InputError, clip
from gcm_pipeline.sources.files.common import (
    ImportedGrasps,
    check_count,
    check_poses,
    score_column,
    width_column,
)
from gcm_pipeline.sources.files.pickled import read_npz_members
from gcm_pipeline.sources.files.sniff import check_format

__all__ = ["CONTACT_COLUMNS", "read_contact_graspnet"]

#: The per-candidate columns of a grasp's contact point [m] (``contact_pts``).
CONTACT_COLUMNS = ("contact_x", "contact_y", "contact_z")


def _segments(value: Any) -> dict[Any, np.ndarray]:
    """A per-segment dict (a 0-d object array holding one, or a plain array = segment -1)."""
    if isinstance(value, np.ndarray) and value.dtype.hasobject and value.ndim == 0:
        value = value.item()
    if isinstance(value, dict):
        return value
    return {-1: value}


def read_contact_graspnet(
    path: str | Path, *, max_count: int = DEFAULT_MAX_CANDIDATES
) -> ImportedGrasps:
    """Read Contact-GraspNet predictions (``pred_grasps_cam`` and friends).

    Segments are read in ascending order of their id; within a segment rows
    stay in file order.

    Args:
        path: The ``.npz`` file.
        max_count: Most grasps the file may hold (``candidates.max_count``);
            its arrays are sized before they are read.

    Returns:
        Gripper base poses (``base`` convention) in the camera frame with
        ``score`` (the file's ``scores``; no column when it has none),
        ``width`` (``gripper_openings`` when present, else NaN),
        ``segment`` (the segment id), ``source_id`` (the row inside its
        segment) and, when the file has ``contact_pts``, the contact point
        in the camera frame as ``contact_x``, ``contact_y``, ``contact_z``
        [m] (NaN for a segment without contact points).

    Raises:
        InputError: Not an ``.npz`` with ``pred_grasps_cam``, inconsistent
            lengths, non-rigid poses.
    """
    path = Path(path)
    check_format(path, "contact_graspnet")
    arrays = read_npz_members(path, max_count)
    if "pred_grasps_cam" not in arrays:
        raise InputError(
            f"{path}: not a Contact-GraspNet prediction file: no array 'pred_grasps_cam' "
            f"(arrays: {', '.join(arrays) or 'none'})",
            path=path,
        )
    grasps = _segments(arrays["pred_grasps_cam"])
    scores = _segments(arrays["scores"]) if "scores" in arrays else {}
    openings = _segments(arrays["gripper_openings"]) if "gripper_openings" in arrays else {}
    contacts = _segments(arrays["contact_pts"]) if "contact_pts" in arrays else None
    _check_contact_segments(path, contacts, grasps)
    try:
        keys = sorted(grasps, key=lambda k: float(k))
    except (TypeError, ValueError):
        keys = sorted(grasps, key=str)
    parts: list[np.ndarray] = []
    cols: dict[str, list[Any]] = {"score": [], "width": [], "segment": [], "source_id": []}
    points: list[np.ndarray] = []
    try:
        total = sum(int(np.size(v)) // 16 for v in grasps.values())
    except (TypeError, ValueError):  # ragged lists
        raise InputError(
            f"{path}: pred_grasps_cam must map segments to (M, 4, 4) arrays of poses", path=path
        ) from None
    check_count(path, total, max_count)
    for key in keys:
        what = f"pred_grasps_cam[{clip(key, 40)}]"
        value = grasps[key]
        raw = value if isinstance(value, np.ndarray) else np.asarray(value, dtype=object)
        if raw.size == 0:
            continue
        if raw.ndim not in (2, 3) or raw.shape[-2:] != (4, 4):
            raise InputError(
                f"{path}: {what} must be an (M, 4, 4) array of poses, got "
                f"{type(value).__name__} of shape {raw.shape}",
                path=path,
            )
        poses = check_poses(path, raw.reshape(-1, 4, 4), what)
        m = len(poses)
        parts.append(poses)
        if "scores" in arrays:  # a file without scores has no score column
            if key not in scores:
                raise InputError(
                    f"{path}: scores has no entry for segment {clip(key, 40)}; "
                    "pred_grasps_cam has one",
                    path=path,
                    key=f"scores[{clip(key, 40)}]",
                )
            cols["score"].append(score_column(path, scores[key], m, f"scores[{clip(key, 40)}]"))
        width = openings.get(key)
        cols["width"].append(
            np.full(m, np.nan)
            if width is None
            else width_column(path, width, m, f"gripper_openings[{clip(key, 40)}]")
        )
        if contacts is not None:
            points.append(_contact_points(path, contacts.get(key), m, key))
        try:
            seg = int(float(key))
        except (TypeError, ValueError, OverflowError):
            seg = keys.index(key)
        if abs(seg) >= 2**62:
            raise InputError(f"{path}: segment id {clip(key, 40)} is not an integer id", path=path)
        cols["segment"].append(np.full(m, seg, dtype=np.int64))
        cols["source_id"].append(np.arange(m, dtype=np.int64))
    if not parts:
        return ImportedGrasps(np.zeros((0, 4, 4)), "base", {})
    columns = {k: np.concatenate(v) for k, v in cols.items() if v}
    if points:
        columns.update(zip(CONTACT_COLUMNS, np.concatenate(points).T, strict=True))
    return ImportedGrasps(np.concatenate(parts), "base", columns)


def _check_contact_segments(path: Path, contacts: dict | None, grasps: dict) -> None:
    """Every segment of ``contact_pts`` has grasps (the file's dicts share their keys)."""
    stray = [k for k in contacts or () if k not in grasps]
    if stray:  # keys off by one would leave every contact point NaN
        raise InputError(
            f"{path}: contact_pts has segment {clip(stray[0], 40)}, which pred_grasps_cam has "
            f"not (its segments: {clip(', '.join(str(k) for k in grasps), 80)})",
            path=path,
            key=f"contact_pts[{clip(stray[0], 40)}]",
        )


def _contact_points(path: Path, value: Any, m: int, key: Any) -> np.ndarray:
    """(m, 3) contact points of a segment [m] (NaN when the file has none for it)."""
    if value is None:
        return np.full((m, 3), np.nan)
    what = f"contact_pts[{clip(key, 40)}]"
    try:
        arr = np.asarray(value, dtype=float)
    except (TypeError, ValueError):
        raise InputError(f"{path}: {what} must be numbers", path=path) from None
    if arr.shape != (m, 3):
        raise InputError(
            f"{path}: {what} must be a ({m}, 3) array of points, one per grasp of "
            f"pred_grasps_cam[{clip(key, 40)}], got shape {arr.shape}",
            path=path,
        )
    if np.isinf(arr).any():
        raise InputError(f"{path}: {what} has an infinite coordinate", path=path)
    return arr
