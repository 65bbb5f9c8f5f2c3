"""Step 2 of the reachability engine: the checks of IK solutions.

At the grasp: the collision checker, then the validator; then the approach
and the retreat (:func:`~gcm_pipeline.reach.move_check.check_moves`), each only for
the solutions that passed the checks before it. A move whose end is proved
beyond reach fails whatever the solution (:meth:`SolutionChecks.hopeless`).
"""

from __future__ import annotations

import time
from collections.abc import Callable, Mapping
from typing import Any

import numpy as np

from gcm_pipeline.errors import InputError
from gcm_pipeline.reach.deviation import gripper_radius
from gcm_pipeline.reach.move_check import check_moves
from gcm_pipeline.reach.moves import Move, unreachable_ends
from gcm_pipeline.reach.options import shared_ik_options
from gcm_pipeline.reach.result import (
    AT_APPROACH,
    AT_GRASP,
    AT_RETREAT,
    PASSED,
    REASON_APPROACH,
    REASON_RETREAT,
    CheckResult,
)
from gcm_pipeline.robot.model import Robot

__all__ = ["SolutionChecks"]


class SolutionChecks:
    """The checks of IK solutions of grasp poses (step 2 of the engine).

    Args:
        robot: The robot.
        checker: A :class:`~gcm_pipeline.robot.collision.CollisionChecker` or None.
        validator: Optional ``q (M, nq) -> (M,) str`` ('' = valid).
        approach: The approach move or None.
        retreat: The retreat move or None.
        backend: IK backend of the moves' waypoints.
        position_tolerance: IK tolerance [m].
        orientation_tolerance: IK tolerance [rad].
        ik_options: The engine's IK options (read at every check).
        spent: ``spent(step, since)`` adds the CPU time since ``since`` to a step.
    """

    def __init__(
        self,
        robot: Robot,
        checker: Any | None,
        validator: Callable[[np.ndarray], Any] | None,
        approach: Move | None,
        retreat: Move | None,
        *,
        backend: str,
        position_tolerance: float,
        orientation_tolerance: float,
        ik_options: Mapping[str, Any],
        spent: Callable[[str, float], None],
    ) -> None:
        self.robot = robot
        self.checker = checker
        self.validator = validator
        self.approach = approach
        self.retreat = retreat
        self.backend = backend
        self.position_tolerance = position_tolerance
        self.orientation_tolerance = orientation_tolerance
        self.ik_options = ik_options
        self.spent = spent
        self.radius = gripper_radius(robot) if (approach or retreat) else 0.0

    def at_grasp(self, q: np.ndarray) -> np.ndarray:
        """The checks at the grasp of M solutions: collisions, then the validator.

        Returns:
            (M,) object array of reasons, ``''`` where both pass.
        """
        m = q.shape[0]
        reason = np.full(m, "", dtype=object)
        t0 = time.process_time()
        if self.checker is not None and m:
            reason[:] = np.asarray(self.checker.check(q), dtype=object)
        self.spent("collisions", t0)
        if self.validator is not None:
            free = np.flatnonzero(reason == "")
            if free.size:
                why = np.asarray(self.validator(q[free]), dtype=object)
                if why.shape != (free.size,):
                    raise InputError(
                        f"validator returned shape {why.shape}, expected ({free.size},)"
                    )
                reason[free] = why
        return reason

    def check(
        self, targets: np.ndarray, q: np.ndarray, at_grasp: np.ndarray | None = None
    ) -> CheckResult:
        """Step 2 for M solutions: collisions, validator, approach, retreat.

        Args:
            targets: Grasp poses (M, 4, 4) in the base frame [m].
            q: Their IK solutions (M, nq) [rad], finite.
            at_grasp: The reasons (M,) of the checks at the grasp (collisions and
                validator, :meth:`at_grasp`) if already known.

        Returns:
            The :class:`CheckResult`.
        """
        m, nq = q.shape
        if at_grasp is None:
            reason = self.at_grasp(q)
        else:
            reason = np.asarray(at_grasp, dtype=object).copy()
        stage = np.where(reason == "", AT_APPROACH, AT_GRASP)
        q_pre = np.full((m, nq), np.nan)
        q_ret = np.full((m, nq), np.nan)
        for move, at, fail, out in (
            (self.approach, AT_APPROACH, REASON_APPROACH, q_pre),
            (self.retreat, AT_RETREAT, REASON_RETREAT, q_ret),
        ):
            rows = np.flatnonzero(stage == at)
            t0 = time.process_time()
            if move is not None and rows.size:
                on = targets.take(rows, axis=0)
                res = check_moves(
                    self.robot,
                    on,
                    q.take(rows, axis=0),
                    move,
                    self.path_collisions(move, on),
                    gripper_radius=self.radius,
                    position_tolerance=self.position_tolerance,
                    orientation_tolerance=self.orientation_tolerance,
                    backend=self.backend,
                    knots=False,  # only the verdicts and the ends are kept
                    **shared_ik_options(self.backend, self.ik_options),
                )
                reason[rows[~res.ok]] = fail
                out[rows] = res.q_end
                rows = rows[res.ok]
            stage[rows] = at + 1
            self.spent(fail, t0)
        return CheckResult(stage == PASSED, stage, reason.astype(str), q_pre, q_ret)

    def hopeless(self, targets: np.ndarray, stage: np.ndarray) -> np.ndarray:
        """Targets (M,) whose solution failed a move that no solution can pass.

        ``stage`` (M,) is how far the target's solution got (:class:`CheckResult`);
        one that failed the approach (or the retreat) whose end is proved beyond
        reach (:func:`~gcm_pipeline.reach.moves.unreachable_ends`) fails it
        whatever the configuration, so no other solution gets further.
        """
        out = np.zeros(len(targets), dtype=bool)
        for move, at in ((self.approach, AT_APPROACH), (self.retreat, AT_RETREAT)):
            rows = np.flatnonzero(stage == at)
            if move is not None and rows.size:
                out[rows] = unreachable_ends(
                    self.robot,
                    targets[rows],
                    move,
                    self.position_tolerance,
                    self.orientation_tolerance,
                )
        return out

    def path_collisions(
        self, move: Move, targets: np.ndarray
    ) -> Callable[[np.ndarray, np.ndarray], Any] | None:
        """The collision check of a move's grid points (None without a checker).

        The approach allows no contact; the retreat holds the object: it moves
        with the grasp frame (its pose in the grasp frame is fixed at the grasp).
        """
        checker = self.checker
        if checker is None:
            return None
        if not move.holding:
            return lambda q, rows: checker.check(q, mode="approach")
        obj = getattr(checker, "object", None)
        if obj is None:
            return lambda q, rows: checker.check(q, mode="retreat")
        held = np.linalg.inv(targets) @ obj.placement
        return lambda q, rows: checker.check(q, mode="retreat", carried=held[rows])
