"""Steps 1-5 of one chunk of targets: the per-target decision of the reachability engine.

:class:`ChunkSteps` is the base of
:class:`~gcm_pipeline.reach.engine.ReachabilityEngine` (whose module doc states
the sequence): its :meth:`~ChunkSteps.solve` is what runs on this process or
on a worker for each chunk of a run. :class:`ChunkAnswers` holds the
per-target answers while the steps fill them in.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Any

import numpy as np

from gcm_pipeline.reach.alternatives import merge_ik, other_solutions
from gcm_pipeline.reach.options import shared_ik_options
from gcm_pipeline.reach.result import AT_APPROACH, AT_GRASP, CheckResult
from gcm_pipeline.reach.solution_checks import SolutionChecks
from gcm_pipeline.reach.workers import blas_controller
from gcm_pipeline.robot.ik import IKResult, PinocchioIKOptions, solve_ik
from gcm_pipeline.robot.model import Robot

__all__ = ["ChunkAnswers", "ChunkSteps"]

#: Seeds of the re-solve (step 3) for the pinocchio backend: library
#: neighbours and random restarts beyond the first solve's.
_RESOLVE_LIBRARY = 8
_RESOLVE_RESTARTS = 0

#: Library seeds of a row whose neighbours all failed IK (step 1; no random restarts).
_HOPELESS_LIBRARY = 2

#: Two solutions closer than this in every joint are the same branch [rad].
_SAME_SOLUTION = 1e-3

#: Seeds of the search for more branches (step 4, pinocchio backend).
_BRANCH_LIBRARY = 16
_BRANCH_RESTARTS = 8


@dataclass
class ChunkAnswers:
    """The per-target answers of one chunk of M targets, filled in by steps 1-3.

    A row keeps the first solution that passes every check; while none has, the
    one whose check got furthest (``best`` stage) gives its ``reason`` and
    ``q_rejected``.
    """

    reachable: np.ndarray
    reason: np.ndarray
    q: np.ndarray
    pos_err: np.ndarray
    rot_err: np.ndarray
    q_pre: np.ndarray
    q_ret: np.ndarray
    q_rejected: np.ndarray
    best: np.ndarray

    @classmethod
    def start(cls, res: IKResult, nq: int) -> ChunkAnswers:
        """No answer yet: the IK's reasons and errors, no solution kept."""
        m = len(res.reason)
        return cls(
            reachable=np.zeros(m, dtype=bool),
            reason=res.reason.astype(object),
            q=np.full((m, nq), np.nan),
            pos_err=res.pos_err.copy(),
            rot_err=res.rot_err.copy(),
            q_pre=np.full((m, nq), np.nan),
            q_ret=np.full((m, nq), np.nan),
            q_rejected=np.full((m, nq), np.nan),
            best=np.full(m, -1),
        )

    def record(
        self, rows: np.ndarray, qs: np.ndarray, err: np.ndarray | None, chk: CheckResult
    ) -> np.ndarray:
        """Keep the passes among solutions ``qs`` of ``rows`` and the furthest failures.

        Args:
            rows: The target of each solution.
            qs: The solutions.
            err: Their IK errors (position, rotation) or None (keep the IK's).
            chk: Their check.

        Returns:
            The rows whose solution failed.
        """
        ok = chk.passed
        self.reachable[rows[ok]] = True
        self.reason[rows[ok]] = ""
        self.q[rows[ok]] = qs[ok]
        self.q_pre[rows[ok]] = chk.q_pregrasp[ok]
        self.q_ret[rows[ok]] = chk.q_retreat[ok]
        if err is not None:
            self.pos_err[rows[ok]], self.rot_err[rows[ok]] = err[ok, 0], err[ok, 1]
        further = ~ok & (chk.stage > self.best[rows])
        self.reason[rows[further]] = chk.reason[further]
        self.q_rejected[rows[further]] = qs[further]
        self.best[rows[further]] = chk.stage[further]
        return rows[~ok]


class ChunkSteps:
    """Steps 1-5 of one chunk, on the settings of the engine that derives from it.

    The attributes are those of
    :class:`~gcm_pipeline.reach.engine.ReachabilityEngine` (set by its constructor).
    """

    robot: Robot
    checker: Any | None
    backend: str
    position_tolerance: float
    orientation_tolerance: float
    alternatives: int
    ik_options: dict[str, Any]
    solutions: int
    solution_separation: float
    timings: dict[str, float]
    _checks: SolutionChecks

    # --- step 2 ------------------------------------------------------------------------

    def check_grasp(self, q: np.ndarray) -> np.ndarray:
        """The checks at the grasp of M solutions: collisions, then the validator.

        See :meth:`~gcm_pipeline.reach.solution_checks.SolutionChecks.at_grasp`.
        """
        return self._checks.at_grasp(q)

    def check(
        self, targets: np.ndarray, q: np.ndarray, at_grasp: np.ndarray | None = None
    ) -> CheckResult:
        """Step 2 for M solutions: collisions, validator, approach, retreat.

        See :meth:`~gcm_pipeline.reach.solution_checks.SolutionChecks.check`.
        """
        return self._checks.check(targets, q, at_grasp)

    def _spent(self, step: str, since: float) -> None:
        """Add the CPU time since ``since`` to ``timings[step]`` [s]."""
        self.timings[step] = self.timings.get(step, 0.0) + time.process_time() - since

    # --- step 3 ------------------------------------------------------------------------

    def _alternatives(
        self,
        targets: np.ndarray,
        q_first: np.ndarray,
        count: int | None = None,
        separation: float = _SAME_SOLUTION,
        library: int = _RESOLVE_LIBRARY,
        restarts: int = _RESOLVE_RESTARTS,
        every_branch: bool | None = None,
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Other verified, distinct IK solutions of M targets, in seed order.

        See :func:`~gcm_pipeline.reach.alternatives.other_solutions`; ``count``
        None: ``alternatives`` per target; every closed-form branch of a 6R arm
        when ``count`` is None or ``every_branch``.
        """
        return other_solutions(
            self.robot,
            targets,
            q_first,
            count=self.alternatives if count is None else int(count),
            every_branch=count is None if every_branch is None else every_branch,
            backend=self.backend,
            position_tolerance=self.position_tolerance,
            orientation_tolerance=self.orientation_tolerance,
            ik_options=self.ik_options,
            shared_options=shared_ik_options(self.backend, self.ik_options),
            separation=separation,
            library=library,
            restarts=restarts,
        )

    def _branches(
        self,
        targets: np.ndarray,
        reachable: np.ndarray,
        q: np.ndarray,
        q_pre: np.ndarray,
        q_ret: np.ndarray,
    ) -> dict[str, np.ndarray]:
        """Step 4: up to ``solutions`` branches per reachable target (arrays ``b_*``)."""
        m, nq, k = len(targets), self.robot.nq, self.solutions
        bq = np.full((m, k, nq), np.nan)
        bpre = np.full((m, k, nq), np.nan)
        bret = np.full((m, k, nq), np.nan)
        count = reachable.astype(np.int64)
        bq[:, 0], bpre[:, 0], bret[:, 0] = q, q_pre, q_ret
        rows = np.flatnonzero(reachable)
        if rows.size:
            idx, rank, alt_q, _ = self._alternatives(
                targets[rows],
                q[rows],
                count=2 * (k - 1),
                separation=self.solution_separation,
                library=_BRANCH_LIBRARY,
                restarts=_BRANCH_RESTARTS,
                # a 6R arm's closed form: every branch (the nearest 2 (K - 1) to home
                # could all fail a check while a farther one passes)
                every_branch=True,
            )
            if len(idx):
                chk = self.check(targets[rows[idx]], alt_q)
                ok = np.flatnonzero(chk.passed)  # sorted by target, then seed order
                i = idx[ok]
                slot = 1 + np.arange(len(i)) - np.searchsorted(i, i, side="left")
                keep = slot < k
                r, sl, o = rows[i[keep]], slot[keep], ok[keep]
                bq[r, sl] = alt_q[o]
                bpre[r, sl] = chk.q_pregrasp[o]
                bret[r, sl] = chk.q_retreat[o]
                np.maximum.at(count, r, sl + 1)
        bclear = np.full((m, k), np.nan)
        if self.checker is not None:
            extra = np.isfinite(bq[:, 1:, 0])
            if extra.any():
                r, j = np.nonzero(extra)
                bclear[r, j + 1] = self.checker.clearance(bq[r, j + 1])
        return {
            "b_q": bq,
            "b_q_pregrasp": bpre,
            "b_q_retreat": bret,
            "b_clearance": bclear,
            "b_count": count,
        }

    # --- one chunk: steps 1-5 -------------------------------------------------------------

    def _first_solve(
        self,
        targets: np.ndarray,
        seeds: np.ndarray | None,
        return_candidates: bool,
        no_restarts: np.ndarray | None,
    ) -> IKResult:
        """Step 1: the IK of every target; ``no_restarts`` rows without random restarts."""

        def ik(rows: np.ndarray, **extra: Any) -> IKResult:
            return solve_ik(
                self.robot,
                targets[rows],
                self.backend,
                position_tolerance=self.position_tolerance,
                orientation_tolerance=self.orientation_tolerance,
                seeds=None if seeds is None else seeds[rows],
                return_all=return_candidates,
                **{**self.ik_options, **extra},
            )

        m = len(targets)
        if no_restarts is None or not np.any(no_restarts):
            return ik(np.arange(m))
        parts = [np.flatnonzero(~no_restarts), np.flatnonzero(no_restarts)]
        small: dict[str, Any] = {"random_restarts": 0}
        if self.backend == "pinocchio":
            lib = self.ik_options.get("library_seeds", PinocchioIKOptions.library_seeds)
            small["library_seeds"] = min(int(lib), _HOPELESS_LIBRARY)
        results = [ik(parts[0]), ik(parts[1], **small)]
        return merge_ik(parts, results, m, self.robot.nq)

    def solve(
        self,
        targets: np.ndarray,
        seeds: np.ndarray | None = None,
        return_candidates: bool = False,
        no_restarts: np.ndarray | None = None,
    ) -> dict[str, Any]:
        """Steps 1-5 for one chunk of validated targets (see the engine's ``run``).

        Args:
            targets: Grasp poses (M, 4, 4) in the base frame [m].
            seeds: Warm starts (M, K, nq) [rad] (NaN = none) or None.
            return_candidates: Also return step 1's converged candidates.
            no_restarts: (M,) bool, targets whose IK gets no random restarts and
                fewer library seeds (every neighbour failed IK after its own
                full schedule), or None.

        Returns:
            The :class:`ReachResult` fields as a dict (``candidates`` as a tuple
            of arrays or None).
        """
        # the engine's parallelism is its worker processes: BLAS runs on one thread
        # (its threads only contend with them, and the matrices here are small)
        with blas_controller().limit(limits=1, user_api="blas"):
            return self._solve(targets, seeds, return_candidates, no_restarts)

    def _solve(
        self,
        targets: np.ndarray,
        seeds: np.ndarray | None,
        return_candidates: bool,
        no_restarts: np.ndarray | None,
    ) -> dict[str, Any]:
        m = targets.shape[0]
        self.timings = {}
        t0 = time.process_time()
        res = self._first_solve(targets, seeds, return_candidates, no_restarts)
        self._spent("ik", t0)
        ans = ChunkAnswers.start(res, self.robot.nq)
        # steps 1-2: the first solution of every target
        rows = np.flatnonzero(res.success)
        qs = res.q[res.success]
        failing = ans.record(rows, qs, None, self.check(targets[rows], qs))
        # step 3: other branches of the targets whose solution failed a check, except
        # where the move it failed ends beyond reach (no branch can pass it)
        failing = failing[~self._checks.hopeless(targets[failing], ans.best[failing])]
        if failing.size and self.alternatives > 0:
            self._resolve(targets, failing, ans)
        ans.q_rejected[ans.reachable] = np.nan
        # step 4: more branches of the reachable targets
        branches = (
            self._branches(targets, ans.reachable, ans.q, ans.q_pre, ans.q_ret)
            if self.solutions > 1
            else None
        )
        # step 5: clearance of the reachable rows (and of every branch)
        clearance = None
        if self.checker is not None:
            t0 = time.process_time()
            clearance = np.full(m, np.nan)
            rows = np.flatnonzero(ans.reachable)
            if rows.size:
                clearance[rows] = self.checker.clearance(ans.q[rows])
            self._spent("clearance", t0)
        out: dict[str, Any] = {
            "reachable": ans.reachable,
            "reason": ans.reason.astype(str),
            "q": ans.q,
            "pos_err": ans.pos_err,
            "rot_err": ans.rot_err,
            "clearance": clearance,
            "q_pregrasp": ans.q_pre,
            "q_retreat": ans.q_ret,
            "q_rejected": ans.q_rejected,
            "candidates": None,
            "timings": dict(self.timings),
        }
        if branches is not None:
            out.update(branches)
            if clearance is not None:
                out["b_clearance"][:, 0] = clearance
        if return_candidates and res.candidates is not None:
            c = res.candidates
            out["candidates"] = (c.index, c.q, c.reason)
        return out

    def _resolve(self, targets: np.ndarray, failing: np.ndarray, ans: ChunkAnswers) -> None:
        """Step 3: other IK solutions of the ``failing`` rows, recorded in ``ans``."""
        nq = self.robot.nq
        t0 = time.process_time()
        idx, rank, alt_q, alt_err = self._alternatives(targets[failing], ans.q_rejected[failing])
        self._spent("alternatives", t0)
        # in rank order: a target's first passing alternative is its answer. The
        # first alternatives are checked alone; of the later ones, the checks at the
        # grasp run in one batch, then the moves (the costly part) rank by rank: a
        # target's next collision-free alternative only while none has passed
        who = failing[idx]  # the target of each alternative
        sel = np.flatnonzero((rank == 0) & ~ans.reachable[who])
        if sel.size:
            ans.record(
                who[sel], alt_q[sel], alt_err[sel], self.check(targets[who[sel]], alt_q[sel])
            )
        sel = np.flatnonzero((rank > 0) & ~ans.reachable[who])
        if sel.size == 0:
            return
        at_grasp = self.check_grasp(alt_q[sel])
        stage = np.where(at_grasp == "", AT_APPROACH, AT_GRASP)
        s = np.flatnonzero(stage == AT_GRASP)  # failed at the grasp: the reasons
        if s.size:
            nan = np.full((s.size, nq), np.nan)
            fails = np.zeros(s.size, dtype=bool)
            chk = CheckResult(fails, stage[s], at_grasp[s].astype(str), nan, nan)
            ans.record(who[sel[s]], alt_q[sel[s]], alt_err[sel[s]], chk)
        pending = np.flatnonzero(stage == AT_APPROACH)  # positions in sel, rank order
        while pending.size:
            pending = pending[~ans.reachable[who[sel[pending]]]]
            if pending.size == 0:
                break
            owner = who[sel[pending]]
            first = np.r_[True, owner[1:] != owner[:-1]]
            take, pending = pending[first], pending[~first]
            rows = sel[take]
            chk = self.check(targets[who[rows]], alt_q[rows], at_grasp[take])
            ans.record(who[rows], alt_q[rows], alt_err[rows], chk)
