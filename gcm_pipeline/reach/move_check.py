r"""Collision checks of straight-line moves along their planned joint paths.

:func:`check_moves` plans the moves (:func:`~gcm_pipeline.reach.path.plan_moves`)
and checks every grid point :math:`s_k, k \ge 1` of each joint path (the grasp
itself, :math:`k = 0`, is the caller's) with the check the caller gives (the
approach: no contact allowed; the retreat: the gripper holds the object, which
moves with it). A move whose first path collides at a grid point gets a second
path with a waypoint at every grid point, so that a collision found does not
depend on where the first path's waypoints fell.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np

from gcm_pipeline.reach.moves import Move, MoveResult
from gcm_pipeline.reach.path import plan_moves
from gcm_pipeline.robot.model import Robot

__all__ = ["check_moves"]


def check_moves(
    robot: Robot,
    poses: Any,
    q_start: Any,
    move: Move,
    collisions: Callable[[np.ndarray, np.ndarray], Any] | None,
    *,
    gripper_radius: float,
    position_tolerance: float = 1e-4,
    orientation_tolerance: float = 1e-3,
    backend: str = "pinocchio",
    knots: bool = True,
    **ik_options: Any,
) -> MoveResult:
    """Plan N moves (:func:`plan_moves`) and check their grid points for collisions.

    A move whose path collides is planned once more with a waypoint at every
    grid point (``grid_knots``) and accepted if that path is free.

    Args:
        robot: The robot.
        poses: Grasp poses (N, 4, 4) in the base frame [m].
        q_start: Configurations reaching them (N, nq) [rad].
        move: The move.
        collisions: ``collisions(q, move) -> reasons``: the collision reason
            (``''`` = free) of configurations ``q`` (K, nq) on the moves with
            indices ``move`` (K,), for the grid points ``k >= 1``; e.g.
            ``lambda q, i: checker.check(q, mode="approach")``. None: no
            collision checks.
        gripper_radius: Largest distance of a gripper point from the grasp frame [m].
        position_tolerance: IK tolerance [m].
        orientation_tolerance: IK tolerance [rad].
        backend: IK backend.
        knots: False: the result's ``knots`` is None (for a caller that needs
            only the verdicts and the paths).
        **ik_options: Further backend options.

    Returns:
        The :class:`MoveResult`.
    """
    opts = dict(
        gripper_radius=gripper_radius,
        position_tolerance=position_tolerance,
        orientation_tolerance=orientation_tolerance,
        backend=backend,
        **ik_options,
    )
    tg = np.asarray(poses, dtype=float)
    if tg.ndim == 2:
        tg = tg[None]
    q0 = np.asarray(q_start, dtype=float)
    if q0.ndim == 1:
        q0 = q0[None]
    plan = plan_moves(robot, tg, q0, move, knots=knots, **opts)
    # the plan's own arrays, changed in place (knots: (N, 8 steps + 1, nq) floats or None)
    ok, failed, q_path, plan_knots, dev = (
        plan.ok,
        plan.failed_step,
        plan.q_path,
        plan.knots,
        plan.deviation,
    )
    reason = plan.reason.astype(object)
    if collisions is not None and move.distance > 0:
        rows = np.flatnonzero(ok)
        hit_rows, why, first = _grid_collisions(collisions, q_path, rows, robot.nq)
        ok[hit_rows] = False
        reason[hit_rows] = why
        failed[hit_rows] = first
        if hit_rows.size:
            # a path that collides gets a second plan with a waypoint at every grid
            # point (on the line within the waypoint tolerance): a collision then
            # does not depend on where the first plan's waypoints fell
            again = plan_moves(
                robot,
                tg[hit_rows],
                q0[hit_rows],
                move,
                grid_knots=True,
                # a waypoint that collides fails its move at once (it is a grid point)
                knot_check=lambda q, i: collisions(q, hit_rows[i]),
                check_first=first,  # where the first path collided
                knots=knots,
                **opts,
            )
            # its grid points are its waypoints, each checked as it was found
            good = np.flatnonzero(again.ok)
            r = hit_rows[good]
            ok[r], reason[r], failed[r] = True, "", 0
            q_path[r], dev[r] = again.q_path[good], again.deviation[good]
            if plan_knots is not None:
                plan_knots[r] = again.knots[good]
    q_path[~ok] = np.nan
    if plan_knots is not None:
        plan_knots[~ok] = np.nan
    dev[~ok] = np.nan
    return MoveResult(ok, reason.astype(str), failed, q_path[:, -1].copy(), q_path, dev, plan_knots)


def _grid_collisions(
    collisions: Callable[[np.ndarray, np.ndarray], Any],
    q_path: np.ndarray,
    rows: np.ndarray,
    nq: int,
    ids: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Rows of ``rows`` whose grid points ``k >= 1`` collide, their first reason and step."""
    if rows.size == 0:
        return rows, np.zeros(0, dtype=object), np.zeros(0, dtype=int)
    steps = q_path.shape[1] - 1
    samples = q_path[:, 1:].take(rows, axis=0).reshape(-1, nq)  # faster than q_path[rows, 1:]
    which = np.repeat(rows if ids is None else ids[rows], steps)
    why = np.asarray(collisions(samples, which)).reshape(rows.size, steps)
    hit = why != ""
    bad = np.flatnonzero(hit.any(axis=1))
    first = np.argmax(hit[bad], axis=1)
    return rows[bad], why[bad, first], first + 1
