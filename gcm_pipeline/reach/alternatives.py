"""Other IK solutions of a grasp: the re-solve of step 3 and the branches of step 4.

Every candidate is verified (Pinocchio FK, tolerances, strictly inside the
limits) and kept only if it is a different arm shape from the solution given
and from the earlier candidates of its target (modulo 2 pi on the joints whose
range exceeds a turn). A 6R arm with a closed form gets every branch of it;
other arms search with the IK backend's seeds. The default backend hands its
candidates over as its stages find them (:class:`_FirstDistinct`): a target
whose first ``count`` alternatives are known gets no more searching (those are
kept either way: later candidates come after them).
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np

from gcm_pipeline.robot.ik import IKCandidates, IKResult, solve_ik, verify_solutions
from gcm_pipeline.robot.ik.analytic_6r import (
    branch_gap,
    same_as_earlier,
    six_r_solver,
    wide_joints,
)
from gcm_pipeline.robot.ik.lm import PinocchioIKOptions
from gcm_pipeline.robot.model import Robot

__all__ = ["merge_ik", "other_solutions"]

#: Most closed-form branches of a 6R arm (EAIK: at most 16); step 3 tries every one.
_MOST_BRANCHES = 16


def other_solutions(
    robot: Robot,
    targets: np.ndarray,
    q_first: np.ndarray,
    *,
    count: int,
    every_branch: bool,
    backend: str,
    position_tolerance: float,
    orientation_tolerance: float,
    ik_options: Mapping[str, Any],
    shared_options: Mapping[str, Any],
    separation: float,
    library: int,
    restarts: int,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Other verified, distinct IK solutions of M targets, in seed order.

    Args:
        robot: The robot.
        targets: (M, 4, 4) poses in the base frame.
        q_first: (M, nq) the solution each must differ from.
        count: Alternatives wanted per target.
        every_branch: A 6R arm's closed form gives every branch (up to
            ``_MOST_BRANCHES``) even if ``count`` is smaller.
        backend: IK backend (without a closed form).
        position_tolerance: [m].
        orientation_tolerance: [rad].
        ik_options: The engine's IK options (``analytic``, ``random_seed``).
        shared_options: The IK options every IK of the engine uses.
        separation: Solutions closer than this in every joint are the same [rad].
        library: Library seeds per target (pinocchio).
        restarts: Random restarts per target (pinocchio).

    Returns:
        ``(index, rank, q, errors)``: target index (K,) into ``targets``,
        rank of the alternative among its target's (K,), solutions (K, nq)
        and ``(pos_err, rot_err)`` stacked (K, 2).
    """
    k = count
    nq = robot.nq
    empty = (np.zeros(0, int), np.zeros(0, int), np.zeros((0, nq)), np.zeros((0, 2)))
    six = None if ik_options.get("analytic", True) is False else six_r_solver(robot)
    if six is not None:
        # every branch in closed form, each at its 2 pi copy nearest home, nearest
        # first; step 3 tries them all (the enumeration is complete and cheap)
        eps = PinocchioIKOptions.limit_epsilon
        idx, cq = six.solve(
            targets[:, :3, :3],
            targets[:, :3, 3],
            robot.lower + eps,
            robot.upper - eps,
            robot.home,
        )
        order = np.lexsort((np.sum((cq - robot.home) ** 2, axis=1), idx))
        idx, cq = idx[order], cq[order]
        if every_branch:
            k = max(k, _MOST_BRANCHES)
    else:
        opts: dict[str, Any]
        if backend == "pinocchio":
            opts = {
                "min_solutions": 2 * (k + 1),
                "first_round_seeds": k + 1,
                "round_seeds": k + 1,
                "library_seeds": library,
                "random_restarts": restarts,
            }
        else:
            opts = {"min_solutions": 2 * (k + 1)}
        opts.update((key, v) for key, v in ik_options.items() if key == "random_seed")
        opts.update(shared_options)
        pick = None
        if backend == "pinocchio":
            pick = _FirstDistinct(
                robot, targets, q_first, k, separation, position_tolerance, orientation_tolerance
            )
        res = solve_ik(
            robot,
            targets,
            backend,
            position_tolerance=position_tolerance,
            orientation_tolerance=orientation_tolerance,
            return_all=True,
            settle=None if pick is None else pick.offer,
            **opts,
        )
        cand = res.candidates
        if pick is not None:
            # every candidate went through pick.offer, in order
            assert cand is not None and pick.seen == len(cand.index)
            return pick.result()
        if cand is None or len(cand.index) == 0:
            return empty
        idx, cq = cand.index, cand.q
    if len(idx) == 0:
        return empty
    return _verified_distinct(
        robot, targets, q_first, idx, cq, k, separation, position_tolerance, orientation_tolerance
    )


def _verified_distinct(
    robot: Robot,
    targets: np.ndarray,
    q_first: np.ndarray,
    idx: np.ndarray,
    cq: np.ndarray,
    k: int,
    separation: float,
    position_tolerance: float,
    orientation_tolerance: float,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Of candidates ``cq`` of targets ``idx`` (sorted by target), the first ``k`` per target.

    Kept: verified (Pinocchio FK within the tolerances, inside the limits) and
    distinct from ``q_first`` and from the target's earlier candidates.
    Returns ``(index, rank, q, errors)`` as :func:`other_solutions`.
    """
    wide = wide_joints(robot.lower, robot.upper)
    idx, cq, err = _verified(
        robot, targets, q_first, idx, cq, wide, separation, position_tolerance,
        orientation_tolerance,
    )  # fmt: skip
    return _first_distinct(idx, cq, err, k, wide, separation)


def _verified(
    robot: Robot,
    targets: np.ndarray,
    q_first: np.ndarray,
    idx: np.ndarray,
    cq: np.ndarray,
    wide: np.ndarray,
    separation: float,
    position_tolerance: float,
    orientation_tolerance: float,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Of candidates ``cq`` of targets ``idx``, those verified and apart from ``q_first``.

    Verified: Pinocchio FK within the tolerances, strictly inside the limits.
    Apart: farther than ``separation`` from the target's first solution in
    some joint (modulo 2 pi on the ``wide`` joints). Returns ``(index, q,
    errors)`` in the given order, errors ``(pos_err, rot_err)`` stacked (K, 2).
    """
    # the first solution's copies go before the verification: dropped either way
    keep = np.max(branch_gap(cq, q_first[idx], wide), axis=1) >= separation
    idx, cq = idx[keep], cq[keep]
    pe, re, inside = verify_solutions(robot, cq, targets[idx])
    good = (pe <= position_tolerance) & (re <= orientation_tolerance) & inside
    return idx[good], cq[good], np.stack([pe[good], re[good]], axis=1)


def _distinct(idx: np.ndarray, cq: np.ndarray, wide: np.ndarray, separation: float) -> np.ndarray:
    """(K,) bool: the candidates (sorted by target) apart from every earlier one of their target."""

    def close(j: int, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        return branch_gap(x[:, None], y[:, None], wide[j : j + 1])[:, 0] < separation

    return ~same_as_earlier(idx, cq, close)


def _first_distinct(
    idx: np.ndarray, cq: np.ndarray, err: np.ndarray, k: int, wide: np.ndarray, separation: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Of verified candidates (sorted by target), the first ``k`` distinct ones per target.

    Distinct: apart from the earlier candidates of the target (in seed order
    within a target), modulo 2 pi on the ``wide`` joints (q + 2 pi is the same
    arm shape). Returns ``(index, rank, q, errors)`` as :func:`other_solutions`.
    """
    empty = (np.zeros(0, int), np.zeros(0, int), np.zeros((0, cq.shape[1])), np.zeros((0, 2)))
    if len(idx) == 0:
        return empty
    distinct = _distinct(idx, cq, wide, separation)
    idx, cq, err = idx[distinct], cq[distinct], err[distinct]
    rank = np.arange(len(idx)) - np.searchsorted(idx, idx, side="left")
    keep = rank < k
    if not np.any(keep):
        return empty
    return idx[keep], rank[keep], cq[keep], err[keep]


class _FirstDistinct:
    """:func:`_verified_distinct` of candidates handed over as the IK finds them.

    :meth:`offer` takes each candidate once, a target's in seed order, verifies
    the new ones and returns the targets whose first ``k`` verified, distinct
    alternatives are known (settled): the IK searches no more for them, and a
    candidate of theirs that still comes is dropped (it would come after those
    ``k``). :meth:`result` is then what :func:`_verified_distinct` gives for all
    the candidates, with each verified once.
    """

    def __init__(
        self,
        robot: Robot,
        targets: np.ndarray,
        q_first: np.ndarray,
        k: int,
        separation: float,
        position_tolerance: float,
        orientation_tolerance: float,
    ) -> None:
        self.robot, self.targets, self.q_first = robot, targets, q_first
        self.k, self.separation = k, separation
        self.tolerances = (position_tolerance, orientation_tolerance)
        self.wide = wide_joints(robot.lower, robot.upper)
        self.settled = np.zeros(len(targets), dtype=bool)
        #: Candidates given so far.
        self.seen = 0
        #: The verified candidates, in the order given: ``(index, q, errors)``.
        self.parts: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = []

    def _all(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The verified candidates so far, sorted by target (in the order given within one)."""
        if not self.parts:
            nq = self.robot.nq
            return np.zeros(0, int), np.zeros((0, nq)), np.zeros((0, 2))
        idx = np.concatenate([p[0] for p in self.parts])
        order = np.argsort(idx, kind="stable")
        return (
            idx[order],
            np.concatenate([p[1] for p in self.parts])[order],
            np.concatenate([p[2] for p in self.parts])[order],
        )

    def offer(self, idx: np.ndarray, cq: np.ndarray) -> np.ndarray:
        """Take candidates ``cq`` (M, nq) of targets ``idx`` (M,); the settled targets (N,)."""
        self.seen += len(idx)
        idx = np.asarray(idx, dtype=int)
        open_ = np.flatnonzero(~self.settled[idx])
        order = open_[np.argsort(idx[open_], kind="stable")]
        vi, vq, ve = _verified(
            self.robot, self.targets, self.q_first, idx[order], cq[order], self.wide,
            self.separation, *self.tolerances,
        )  # fmt: skip
        if len(vi) == 0:
            return self.settled
        self.parts.append((vi, vq, ve))
        # distinct alternatives of the targets just given more, over all of theirs
        ai, aq, _ = self._all()
        mine = np.isin(ai, vi)
        ai, aq = ai[mine], aq[mine]
        found = np.bincount(
            ai[_distinct(ai, aq, self.wide, self.separation)], minlength=len(self.settled)
        )
        self.settled |= found >= self.k
        return self.settled

    def result(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """``(index, rank, q, errors)`` as :func:`other_solutions`."""
        idx, cq, err = self._all()
        return _first_distinct(idx, cq, err, self.k, self.wide, self.separation)


def merge_ik(parts: list[np.ndarray], results: list[IKResult], m: int, nq: int) -> IKResult:
    """One :class:`IKResult` of M targets from results of row subsets ``parts``."""
    q = np.full((m, nq), np.nan)
    success = np.zeros(m, dtype=bool)
    pos_err = np.full(m, np.nan)
    rot_err = np.full(m, np.nan)
    reason = np.full(m, "", dtype=object)
    for rows, r in zip(parts, results, strict=True):
        q[rows], success[rows], reason[rows] = r.q, r.success, r.reason
        pos_err[rows], rot_err[rows] = r.pos_err, r.rot_err
    candidates = None
    if results[0].candidates is not None:
        cands = [r.candidates for r in results if r.candidates is not None]
        index = np.concatenate([rows[c.index] for rows, c in zip(parts, cands, strict=True)])
        order = np.argsort(index, kind="stable")
        candidates = IKCandidates(
            index[order],
            np.concatenate([c.q for c in cands]).reshape(-1, nq)[order],
            np.concatenate([c.reason for c in cands])[order],
        )
    return IKResult(
        q, success, pos_err, rot_err, reason.astype(str), results[0].backend, candidates
    )
