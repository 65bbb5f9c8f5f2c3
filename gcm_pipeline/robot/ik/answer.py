"""The raw answer of an IK backend, before :func:`~gcm_pipeline.robot.ik.solve_ik` verifies it."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

__all__ = ["BackendAnswer"]


@dataclass(frozen=True, eq=False)
class BackendAnswer:
    """A backend's raw, unverified answer for N targets.

    Attributes:
        q: Chosen configuration per target (N, nq) [rad], NaN if none.
        success: (N,) bool: the backend converged to a valid configuration.
        pos_err: Position error (N,) [m] of the chosen or best attempt.
        rot_err: Orientation error (N,) [rad] of the chosen or best attempt.
        reason: (N,) why a target failed, ``''`` for successes.
        all_index: With ``return_all``: target row of every converged candidate (M,).
        all_q: With ``return_all``: the candidates (M, nq) [rad].
        all_reason: With ``return_all``: validator reason per candidate (M,).
    """

    q: np.ndarray
    success: np.ndarray
    pos_err: np.ndarray
    rot_err: np.ndarray
    reason: np.ndarray
    all_index: np.ndarray | None = None
    all_q: np.ndarray | None = None
    all_reason: np.ndarray | None = None

    @classmethod
    def concatenate(
        cls, parts: Sequence[BackendAnswer], starts: Sequence[int], with_candidates: bool
    ) -> BackendAnswer:
        """One answer from the answers of consecutive chunks of targets.

        Args:
            parts: Answers of the chunks, in order.
            starts: First target row of each chunk.
            with_candidates: Concatenate the ``all_*`` candidates too
                (re-indexed to the whole batch).
        """
        cand: dict[str, np.ndarray | None] = {}
        if with_candidates:
            cand["all_index"] = np.concatenate(
                [_given(p.all_index) + a for p, a in zip(parts, starts, strict=False)]
            )
            cand["all_q"] = np.concatenate([_given(p.all_q) for p in parts])
            cand["all_reason"] = np.concatenate([_given(p.all_reason) for p in parts])
        return cls(
            q=np.concatenate([p.q for p in parts]),
            success=np.concatenate([p.success for p in parts]),
            pos_err=np.concatenate([p.pos_err for p in parts]),
            rot_err=np.concatenate([p.rot_err for p in parts]),
            reason=np.concatenate([p.reason for p in parts]),
            **cand,
        )


def _given(arr: np.ndarray | None) -> np.ndarray:
    if arr is None:
        raise ValueError("a backend answered without the candidates return_all asks for")
    return arr
