"""IK of the waypoints on a move's line: the end of the move and the interior waypoints.

The end of a move is solved from the grasp's configuration only (a solution
elsewhere is of no use): with the Panda's closed form first, at joint-7 values
around the start's, then Levenberg-Marquardt from the start. Interior
waypoints converge to a small share of the deviation budget, not to the IK
tolerance: their error is part of what the deviation bound
(:mod:`~gcm_pipeline.reach.deviation`) measures.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from gcm_pipeline.robot.ik import solve_ik, verify_solutions
from gcm_pipeline.robot.ik.candidates import first_smallest
from gcm_pipeline.robot.ik.lm import PinocchioIKOptions, levenberg_marquardt, pose_errors
from gcm_pipeline.robot.ik.panda import analytic_blocks, analytic_solver
from gcm_pipeline.robot.model import Robot

__all__ = ["KNOT_TOLERANCE", "end_of_move", "largest_change", "line_waypoints", "max_over_joints"]

#: Interior waypoints converge to this share of ``max_deviation`` (position) and
#: of ``max_deviation / gripper_radius`` (orientation): their error is part of
#: the deviation the bound measures, not an IK tolerance.
KNOT_TOLERANCE = 0.05
#: LM options of the interior waypoints (they start close: early stall exits).
_KNOT_OPTIONS = PinocchioIKOptions()

#: Joint-7 offsets [rad] around the start's where the closed form looks for the end of a
#: move, and the largest joint change [rad] of an end it keeps (else LM from the start).
_END_Q7 = np.array([0.0, -0.01, 0.01, -0.025, 0.025, -0.05, 0.05, -0.1, 0.1, -0.2, 0.2])
_NEAR_END = 0.3


def end_of_move(
    robot: Robot,
    ends: np.ndarray,
    q_start: np.ndarray,
    backend: str,
    position_tolerance: float,
    orientation_tolerance: float,
    ik_options: dict[str, Any],
) -> tuple[np.ndarray, np.ndarray]:
    """IK of the end poses (M, 4, 4) seeded only from ``q_start`` (M, nq).

    With the Panda's closed form (pinocchio backend) the end is first solved at
    joint-7 values around the start's (offsets up to 0.2 rad), keeping the
    solution whose largest joint change from the start is smallest, if that is
    at most ``_NEAR_END`` [rad]. The other rows (no such solution: a window of
    joint 7 between the samples, or a far end) get LM from the start, as
    without the closed form.

    Returns:
        ``(q, reached)``: configurations (M, nq) and whether each reaches its
        pose within the IK tolerances (verified by Pinocchio FK, strictly
        inside the limits).
    """
    m = len(ends)
    if backend != "pinocchio":
        res = solve_ik(
            robot,
            ends,
            backend,
            position_tolerance=position_tolerance,
            orientation_tolerance=orientation_tolerance,
            seeds=q_start[:, None, :],
            **ik_options,
        )
        return res.q, res.success
    opts = PinocchioIKOptions.from_kwargs(ik_options)
    q = np.full((m, robot.nq), np.nan)
    conv = np.zeros(m, dtype=bool)
    solver = analytic_solver(robot) if opts.analytic else None
    if solver is not None and m:
        eps = opts.limit_epsilon
        lower, upper = robot.lower + eps, robot.upper - eps
        start = np.clip(q_start, lower, upper)
        q7 = np.clip(start[:, 6:7] + _END_Q7, lower[6], upper[6])
        # only ends within _NEAR_END of the start in every joint can be kept
        at, cand, _, _ = analytic_blocks(
            solver, ends[:, :3, :3], ends[:, :3, 3], q7, lower, upper, (start, _NEAR_END)
        )
        # (rows by np.take: NumPy's fancy indexing gathers them several times slower)
        change = largest_change(cand, start.take(at, axis=0))
        first = first_smallest(at, change)  # per end, the solution changing least
        near = first[change[first] <= _NEAR_END]
        # exact away from singularities: a pick off its pose leaves the row to the LM
        tol_p = position_tolerance * opts.inner_tolerance
        tol_r = orientation_tolerance * opts.inner_tolerance
        end = ends.take(at.take(near), axis=0)
        pe, re = pose_errors(
            robot.chain,
            cand.take(near, axis=0),
            np.ascontiguousarray(end[:, :3, :3]),
            np.ascontiguousarray(end[:, :3, 3]),
        )
        near = near[(pe <= tol_p) & (re <= tol_r)]
        q[at[near]], conv[at[near]] = cand[near], True
    rest = np.flatnonzero(~conv)
    if rest.size:
        q[rest], conv[rest] = _lm_inside(
            robot,
            q_start.take(rest, axis=0),
            ends.take(rest, axis=0),
            position_tolerance * opts.inner_tolerance,
            orientation_tolerance * opts.inner_tolerance,
            opts,
        )
    reached = np.zeros(m, dtype=bool)
    rows = np.flatnonzero(conv)
    pe, re, inside = verify_solutions(robot, q.take(rows, axis=0), ends.take(rows, axis=0))
    reached[rows] = (pe <= position_tolerance) & (re <= orientation_tolerance) & inside
    return q, reached


def largest_change(q: np.ndarray, ref: np.ndarray) -> np.ndarray:
    """``np.max(np.abs(q - ref), axis=1)`` of (M, nq) arrays, NaN staying NaN."""
    return max_over_joints(np.abs(q - ref))


def max_over_joints(d: np.ndarray) -> np.ndarray:
    """``np.max(d, axis=-1)``, NaN staying NaN, in one pass per joint (the last axis).

    NumPy reduces a short last axis slowly (5,000 rows of 7 joints: 24 us
    instead of 384 us).
    """
    out = d[..., 0].copy()
    for j in range(1, d.shape[-1]):
        np.maximum(out, d[..., j], out=out)
    return out


def line_waypoints(
    robot: Robot, seed: np.ndarray, target: np.ndarray, tol: float, radius: float
) -> tuple[np.ndarray, np.ndarray]:
    """Waypoints on the line: configurations (M, nq) near ``target`` poses (M, 4, 4).

    Batched Levenberg-Marquardt from ``seed`` (M, nq), inside the joint limits,
    to ``KNOT_TOLERANCE`` of the deviation budget ``tol`` [m] (the orientation
    scaled by the gripper ``radius`` [m]). Returns ``(q, converged)``.
    """
    return _lm_inside(
        robot,
        seed,
        target,
        KNOT_TOLERANCE * tol,
        KNOT_TOLERANCE * tol / max(radius, 1e-3),
        _KNOT_OPTIONS,
    )


def _lm_inside(
    robot: Robot,
    seed: np.ndarray,
    target: np.ndarray,
    tol_p: float,
    tol_r: float,
    opts: PinocchioIKOptions,
) -> tuple[np.ndarray, np.ndarray]:
    """Batched LM from ``seed`` (M, nq) to ``target`` poses (M, 4, 4).

    Kept ``opts.limit_epsilon`` inside the joint limits; returns ``(q, converged)``.
    """
    eps = opts.limit_epsilon
    lower, upper = robot.lower + eps, robot.upper - eps
    q, conv, _, _ = levenberg_marquardt(
        robot.chain,
        np.clip(seed, lower, upper),
        target[:, :3, :3],
        target[:, :3, 3],
        lower,
        upper,
        tol_p,
        tol_r,
        opts,
    )
    return q, conv
