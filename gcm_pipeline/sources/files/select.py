"""Which grasps of a file a run keeps: ``success_only``, ``min_score``, then ``limit``.

In that order: ``success_only`` keeps the grasps labelled successful (by
default, ``None``, whenever the file labels them: ACRONYM's negatives are
grasps its simulation saw fail, not candidates),
``min_score`` those whose ``score`` (the file's quality, see
:mod:`gcm_pipeline.sources.files`) is at least it, and ``limit`` keeps the
best ``limit`` of the rest by ``score`` when the file has one (ties: the
earlier row), else the first ``limit`` in file order. Kept grasps stay in file
order. The log says which rule ``limit`` used, and :class:`Selection` records
it (the run's ``summary.json``, ``selection``).
"""

from __future__ import annotations

import logging
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np

from gcm_pipeline.errors import InputError

__all__ = ["SCORE_SOURCES", "Selection", "select_grasps"]

log = logging.getLogger(__name__)

#: Where each format keeps the grasps' quality (the ``score`` column).
SCORE_SOURCES = (
    "npz: array 'score', csv: column 'score', acronym: grasps/qualities/flex/object_in_gripper, "
    "graspgen: confidences, contact_graspnet: scores, graspnet: column 0"
)

_SUCCESS_SOURCES = (
    "npz: 'success' array, csv: 'success' column, acronym: "
    "grasps/qualities/flex/object_in_gripper, graspgen: grasps.object_in_gripper"
)


@dataclass(frozen=True)
class Selection:
    """What :func:`select_grasps` kept of a file, and how.

    Attributes:
        read: Grasps in the file.
        kept: Grasps kept.
        success_only: Whether only the grasps labelled successful were kept.
        min_score: ``candidates.min_score`` (None: not set).
        limit: ``candidates.limit`` (None: not set).
        limit_by: ``score`` (the best by score) or ``file order`` (the first;
            the file has no score); None without ``limit``.
    """

    read: int
    kept: int
    success_only: bool
    min_score: float | None
    limit: int | None
    limit_by: str | None

    def as_dict(self) -> dict[str, Any]:
        """A JSON-ready dict of the fields."""
        return asdict(self)


def _successful(
    path: str | Path, what: str, n: int, success: np.ndarray | None, success_only: bool | None
) -> tuple[np.ndarray, bool]:
    """The rows ``success_only`` keeps (ascending), and whether it filtered by success."""
    keep = np.arange(n)
    if success_only:
        if success is None:
            raise InputError(
                f"{path}: candidates.success_only needs success labels, but {what} has none "
                f"({_SUCCESS_SOURCES})",
                path=path,
                key="candidates.success_only",
            )
    elif success_only is False or success is None:
        return keep, False
    keep = keep[np.asarray(success, dtype=bool)]  # asked for, or the file labels success
    if n and not keep.size:
        raise InputError(
            f"{path}: none of its {n} grasps is labelled successful "
            "(candidates.success_only: false keeps them all)",
            path=path,
            key="candidates.success_only",
        )
    log.info(
        "candidates: %s: keeps the %d of %d grasps labelled successful "
        "(candidates.success_only: false keeps them all)",
        *(path, keep.size, n),
    )
    return keep, True


def select_grasps(
    path: str | Path,
    fmt: str | None,
    columns: dict[str, np.ndarray],
    success: np.ndarray | None,
    *,
    success_only: bool | None = None,
    min_score: float | None = None,
    limit: int | None = None,
) -> tuple[np.ndarray, Selection]:
    """The rows of a file to keep (ascending), and what was done.

    Args:
        path: The file (for messages).
        fmt: Its format (for messages).
        columns: Its per-grasp columns (``score`` when it has one).
        success: (N,) bool success labels, or None.
        success_only: Keep only the grasps labelled successful; None: when
            the file has success labels.
        min_score: Keep only grasps with ``score >= min_score``.
        limit: Keep at most this many: the best by ``score`` (ties: file
            order), else the first.

    Returns:
        ``(rows, selection)``: 0-based rows of the file, ascending.

    Raises:
        InputError: ``success_only`` without success labels, ``min_score``
            without a score (names the key and the file).
    """
    n = len(columns["source_id"])
    what = f"this {fmt} file" if fmt else "this file"
    keep, success_only = _successful(path, what, n, success, success_only)
    score = columns.get("score")
    if min_score is not None:
        if score is None:
            raise InputError(
                f"{path}: candidates.min_score needs a score per grasp, but {what} has none "
                f"({SCORE_SOURCES})",
                path=path,
                key="candidates.min_score",
                value=min_score,
            )
        before = keep.size
        scores = score[keep]
        keep = keep[scores >= min_score]
        if before and not keep.size:
            raise InputError(
                f"{path}: candidates.min_score {min_score:g} keeps none of its {before} grasps "
                f"(their scores are {scores.min():.4g} to {scores.max():.4g})",
                path=path,
                key="candidates.min_score",
                value=min_score,
            )
        log.info(
            "candidates: %s: min_score %g keeps %d of %d grasps", path, min_score, keep.size, before
        )
    limit_by = None
    if limit is not None:
        limit_by = "file order" if score is None else "score"
        if keep.size > limit and score is not None:
            best = np.argsort(-score[keep], kind="stable")[:limit]  # stable: ties by row
            chosen = np.sort(keep[best])
            log.info(
                "candidates: %s: limit %d keeps the best %d of %d grasps by score "
                "(%.4g to %.4g; ties: the earlier row)",
                *(path, limit, limit, keep.size, score[chosen].min(), score[chosen].max()),
            )
            keep = chosen
        elif keep.size > limit:
            log.info(
                "candidates: %s: limit %d keeps the first %d of %d grasps in file order "
                "(the file has no score)",
                *(path, limit, limit, keep.size),
            )
            keep = keep[:limit]
        else:
            log.info("candidates: %s: limit %d keeps all %d grasps", path, limit, keep.size)
    selection = Selection(n, int(keep.size), bool(success_only), min_score, limit, limit_by)
    return keep, selection
