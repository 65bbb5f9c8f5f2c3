"""What the reachability engine returns: its reasons and its typed results."""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from gcm_pipeline.robot.ik import IKCandidates

__all__ = [
    "AT_APPROACH",
    "AT_GRASP",
    "AT_RETREAT",
    "PASSED",
    "REASON_APPROACH",
    "REASON_RETREAT",
    "Branches",
    "CheckResult",
    "ReachResult",
]

#: Why a grasp fails its approach or its retreat (``ReachResult.reason``).
REASON_APPROACH = "approach"
REASON_RETREAT = "retreat"

#: How far a solution got through the checks of step 2 (``CheckResult.stage``).
AT_GRASP, AT_APPROACH, AT_RETREAT, PASSED = 0, 1, 2, 3


class CheckResult(NamedTuple):
    """Step 2 for M solutions (:meth:`~gcm_pipeline.reach.engine.ReachabilityEngine.check`).

    Attributes:
        passed: (M,) bool, every check passed.
        stage: (M,) int, how far the solution got: 0 failed at the grasp
            (collision or validator), 1 failed the approach, 2 failed the
            retreat, 3 passed.
        reason: (M,) str, ``''`` or why it failed.
        q_pregrasp: (M, nq) [rad] end of the approach (NaN without an approach
            or where it failed).
        q_retreat: (M, nq) [rad] end of the retreat (NaN likewise).
    """

    passed: np.ndarray
    stage: np.ndarray
    reason: np.ndarray
    q_pregrasp: np.ndarray
    q_retreat: np.ndarray


class Branches(NamedTuple):
    """Up to K verified solutions per target that pass every check (step 4).

    Attributes:
        q: (N, K, nq) [rad]; branch 0 is the answer of steps 1-3 (``ReachResult.q``);
            NaN past ``count``.
        q_pregrasp: (N, K, nq) [rad] end of each branch's approach (NaN likewise).
        q_retreat: (N, K, nq) [rad] end of each branch's retreat.
        clearance: (N, K) [m] distance of the arm to the world, or None
            without a collision checker.
        count: (N,) int, branches kept (0 for unreachable targets).
    """

    q: np.ndarray
    q_pregrasp: np.ndarray
    q_retreat: np.ndarray
    clearance: np.ndarray | None
    count: np.ndarray  # type: ignore[assignment]  # the field shadows tuple.count


class ReachResult(NamedTuple):
    """Result of :meth:`~gcm_pipeline.reach.engine.ReachabilityEngine.run` for N targets.

    Attributes:
        reachable: (N,) bool.
        reason: (N,) str, ``''`` when reachable (see the module doc).
        q: (N, nq) [rad] the solution; NaN rows when unreachable.
        pos_err: (N,) [m] position error of the solution, or of the best IK
            attempt when unreachable (NaN if none was made).
        rot_err: (N,) [rad] orientation error, same rules.
        clearance: (N,) [m] distance of the arm to the world (NaN when
            unreachable), or None without a collision checker.
        q_pregrasp: (N, nq) [rad] pre-grasp configuration (NaN when unreachable
            or without an approach).
        q_retreat: (N, nq) [rad] configuration at the end of the retreat.
        q_rejected: (N, nq) [rad] for unreachable rows that had an IK solution,
            the solution that failed the furthest check; NaN otherwise.
        candidates: Every converged IK candidate of step 1 (``return_candidates``).
        branches: Every kept branch when the engine keeps several
            (``solutions`` > 1), else None.
    """

    reachable: np.ndarray
    reason: np.ndarray
    q: np.ndarray
    pos_err: np.ndarray
    rot_err: np.ndarray
    clearance: np.ndarray | None
    q_pregrasp: np.ndarray
    q_retreat: np.ndarray
    q_rejected: np.ndarray
    candidates: IKCandidates | None = None
    branches: Branches | None = None

    def __repr__(self) -> str:
        n = len(self.reachable)
        ok = int(np.count_nonzero(self.reachable))
        names, counts = np.unique(self.reason[~self.reachable].astype(str), return_counts=True)
        fails = ", ".join(f"{r}: {c}" for r, c in zip(names, counts, strict=True))
        return f"ReachResult({ok}/{n} reachable" + (f", {{{fails}}}" if fails else "") + ")"
