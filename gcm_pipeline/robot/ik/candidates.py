"""What the stages of one default-backend solve share: the targets and the tally of candidates.

:func:`~gcm_pipeline.robot.ik.pinocchio_backend.solve` runs in stages (closed
forms, seeded LM rounds, the manipulability raise). Each stage gets one
:class:`SolveContext` (targets, limits, tolerances, options) and offers its
converged candidates to the context's :class:`Tally`, which applies the
validator, counts valid solutions per target, keeps the best one, records the
best attempt of each target (for the error report of failures) and, with
``return_all``, every candidate; a ``settle`` callback given those candidates
between the stages may mark targets that need no more (the later stages skip
them).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from gcm_pipeline.errors import InputError
from gcm_pipeline.robot.ik.lm import PinocchioIKOptions, yoshikawa_of

__all__ = ["SolveContext", "Tally", "first_smallest", "rank_in_runs"]


def rank_in_runs(key: np.ndarray) -> np.ndarray:
    """Position of each element in its run of equal consecutive ``key`` values."""
    start = np.flatnonzero(np.r_[True, key[1:] != key[:-1]])
    return np.arange(key.size) - np.repeat(start, np.diff(np.r_[start, key.size]))


def first_smallest(key: np.ndarray, value: np.ndarray) -> np.ndarray:
    """Per distinct ``key``, in key order, the index of its smallest ``value`` (the first of ties).

    The rows a stable sort by ``(key, value)`` puts first in each group
    (``np.lexsort((value, key))``); without sorting when ``key`` is
    non-decreasing and ``value`` finite (candidates grouped by target).
    """
    key, value = np.asarray(key), np.asarray(value)
    if key.size == 0:
        return np.zeros(0, dtype=np.intp)
    if np.all(key[1:] >= key[:-1]) and np.all(np.isfinite(value)):
        start = np.flatnonzero(np.r_[True, key[1:] != key[:-1]])
        low = np.minimum.reduceat(value, start)
        hit = np.flatnonzero(value == np.repeat(low, np.diff(np.r_[start, key.size])))
        return hit[np.r_[True, key[hit[1:]] != key[hit[:-1]]]]
    order = np.lexsort((value, key))
    return order[np.r_[True, key[order[1:]] != key[order[:-1]]]]


@dataclass(eq=False)
class Tally:
    """Converged candidates of N targets, as the stages offer them.

    Attributes:
        chain: The robot's kinematic chain (manipulability of candidates).
        validator: Optional ``q (M, nq) -> (M,) str`` reasons ('' = valid).
        return_all: Keep every candidate (``all_index``, ``all_q``, ``all_reason``).
        by_manipulability: Among several valid solutions of a target, keep the
            one of best manipulability (else the one of highest rank).
        best_q: The chosen solution per target (N, nq) [rad], NaN if none.
        best_score: Its score (N,).
        n_valid: Valid solutions per target (N,).
        att_p: Position error of the best attempt per target (N,) [m].
        att_r: Orientation error of the best attempt per target (N,) [rad].
        att_q: Configuration of the best attempt (N, nq) [rad].
        last_reason: The validator's last reason per target (N,), '' if none.
        settle: Optional ``(index (M,), q (M, nq)) -> (N,) bool``: with
            ``return_all``, given every candidate once, in the order recorded
            (:meth:`checkpoint`); returns the targets that need no more candidates.
        settled: Targets (N,) the stages skip (``settle`` said so).
    """

    chain: Any
    validator: Callable[[np.ndarray], np.ndarray] | None
    return_all: bool
    by_manipulability: bool
    best_q: np.ndarray
    best_score: np.ndarray
    n_valid: np.ndarray
    att_p: np.ndarray
    att_r: np.ndarray
    att_q: np.ndarray
    last_reason: np.ndarray
    all_index: list[np.ndarray] = field(default_factory=list)
    all_q: list[np.ndarray] = field(default_factory=list)
    all_reason: list[np.ndarray] = field(default_factory=list)
    settle: Callable[[np.ndarray, np.ndarray], np.ndarray] | None = None
    settled: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=bool))
    #: Blocks of ``all_index`` already given to ``settle``.
    offered: int = 0

    @classmethod
    def empty(
        cls,
        n: int,
        nq: int,
        chain: Any,
        validator: Callable[[np.ndarray], np.ndarray] | None,
        return_all: bool,
        by_manipulability: bool,
        settle: Callable[[np.ndarray, np.ndarray], np.ndarray] | None = None,
    ) -> Tally:
        """A tally of ``n`` targets without any candidate yet."""
        if settle is not None and not return_all:
            raise InputError("settle needs return_all (it is given the candidates)")
        return cls(
            chain=chain,
            validator=validator,
            return_all=return_all,
            by_manipulability=by_manipulability,
            best_q=np.full((n, nq), np.nan),
            best_score=np.full(n, -np.inf),
            n_valid=np.zeros(n, dtype=int),
            att_p=np.full(n, np.inf),
            att_r=np.full(n, np.inf),
            att_q=np.full((n, nq), np.nan),
            last_reason=np.full(n, "", dtype=object),
            settle=settle,
            settled=np.zeros(n, dtype=bool),
        )

    def checkpoint(self) -> None:
        """Give ``settle`` the candidates recorded since the last checkpoint; mark the settled."""
        if self.settle is None or self.offered == len(self.all_index):
            return
        new = slice(self.offered, len(self.all_index))
        self.offered = len(self.all_index)
        index = np.concatenate(self.all_index[new])
        q = np.concatenate(self.all_q[new])
        self.settled |= np.asarray(self.settle(index, q), dtype=bool)

    def accept(self, cids: np.ndarray, cq: np.ndarray, rank: np.ndarray) -> None:
        """Record converged candidates ``cq`` of targets ``cids``.

        ``rank``: higher wins (when not by manipulability).
        """
        if self.validator is not None:
            reasons = np.asarray(self.validator(cq), dtype=object)
            if reasons.shape != (cq.shape[0],):
                raise InputError(
                    f"validator returned shape {reasons.shape}, expected ({cq.shape[0]},)"
                )
        else:
            reasons = np.full(cq.shape[0], "", dtype=object)
        if self.return_all:
            self.all_index.append(cids)
            self.all_q.append(cq)
            self.all_reason.append(reasons)
        valid = reasons == ""
        self.last_reason[cids[~valid]] = reasons[~valid]
        if not np.any(valid):
            return
        vids, vq = cids[valid], cq[valid]
        score = yoshikawa_of(self.chain, vq) if self.by_manipulability else rank[valid]
        np.add.at(self.n_valid, vids, 1)
        order = np.argsort(score, kind="stable")  # ascending: the best is written last
        vids, vq, score = vids[order], vq[order], score[order]
        better = score > self.best_score[vids]
        self.best_q[vids[better]] = vq[better]
        self.best_score[vids[better]] = score[better]

    def attempted(self, ids: np.ndarray, pe: np.ndarray, re: np.ndarray, q: np.ndarray) -> None:
        """Record converged attempts ``q`` of targets ``ids`` with their errors."""
        self.att_p[ids], self.att_r[ids], self.att_q[ids] = pe, re, q


@dataclass(frozen=True, eq=False)
class SolveContext:
    """The targets of one solve call and what every stage of it needs.

    Attributes:
        robot: The robot (its chain, home, caches).
        trot: Target rotations (N, 3, 3), C-contiguous.
        tpos: Target positions (N, 3) [m], C-contiguous.
        lower: Lower joint limits (nq,) [rad], ``limit_epsilon`` inside.
        upper: Upper joint limits (nq,) [rad], ``limit_epsilon`` inside.
        tol_p: Convergence threshold on the position error [m] (the user's
            tolerance times ``inner_tolerance``).
        tol_r: Convergence threshold on the orientation error [rad].
        position_tolerance: The user's position tolerance [m].
        orientation_tolerance: The user's orientation tolerance [rad].
        opts: The backend's options.
        tally: Where the stages offer their candidates.
    """

    robot: Any
    trot: np.ndarray
    tpos: np.ndarray
    lower: np.ndarray
    upper: np.ndarray
    tol_p: float
    tol_r: float
    position_tolerance: float
    orientation_tolerance: float
    opts: PinocchioIKOptions
    tally: Tally

    @property
    def chain(self) -> Any:
        """The robot's kinematic chain."""
        return self.robot.chain

    @property
    def n(self) -> int:
        """Number of targets."""
        return int(self.trot.shape[0])

    @property
    def validate(self) -> bool:
        """Whether a validator judges the candidates."""
        return self.tally.validator is not None

    @property
    def first(self) -> int:
        """Seeds solved at once in the first round (at least 1)."""
        return max(1, self.opts.first_round_seeds)

    @property
    def by_manipulability(self) -> bool:
        """Whether a target keeps its solution of best manipulability among several."""
        return self.tally.by_manipulability

    def short(self) -> np.ndarray:
        """Targets still short of ``opts.min_solutions`` valid solutions and not settled."""
        tally = self.tally
        return np.flatnonzero((tally.n_valid < self.opts.min_solutions) & ~tally.settled)

    @property
    def one_each(self) -> bool:
        """One answer per target (a validator or ``return_all`` does not change which)."""
        return not (self.opts.min_solutions > 1 or self.by_manipulability)
