r"""Straight-line moves of the grasp frame: the pre-grasp approach and the post-grasp retreat.

A move starts at a grasp pose :math:`T_g` (reached by :math:`q_g`) and
translates the grasp frame by a vector :math:`d` (base frame) at fixed
orientation:

.. math::

    T(s) = \operatorname{translate}(s\,d)\,T_g, \qquad s \in [0, 1].

The **approach** is the move with :math:`d = -\mathrm{distance}\,z_g` (the
pre-grasp lies behind the grasp along its approach axis; the robot runs it
from :math:`s = 1` to :math:`s = 0`); the **retreat** moves ``distance`` along a
direction given in the base or the grasp frame (see :class:`Move`). Both are
computed from the grasp outwards.

The joint path of a move is planned by :func:`~gcm_pipeline.reach.path.plan_moves`
and checked for collisions by :func:`~gcm_pipeline.reach.move_check.check_moves`;
the bound of its deviation from the line is :mod:`~gcm_pipeline.reach.deviation`.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple

import numpy as np

from gcm_pipeline.errors import InputError
from gcm_pipeline.robot.ik.panda import analytic_solver
from gcm_pipeline.robot.ik.reach_6r import six_r_reach
from gcm_pipeline.robot.model import Robot

__all__ = [
    "MOVE_REASONS",
    "Move",
    "MovePlan",
    "MoveResult",
    "move_poses",
    "unreachable_ends",
]

#: Why a move fails (``MoveResult.reason``), besides the checker's collision reasons.
MOVE_REASONS = ("invalid", "no_ik", "joint_step", "deviation")


@dataclass(frozen=True)
class Move:
    """A straight-line move of the grasp frame (plain values; the stage maps the config).

    Attributes:
        distance: Length of the move [m], >= 0 (0: nothing to check).
        direction: Direction (3,), normalised here; in the grasp frame
            (``frame="grasp"``) or the robot's base frame (``frame="base"``).
        frame: ``"grasp"`` or ``"base"``.
        steps: Grid steps along the line (collision samples, finest waypoints), >= 1.
        max_joint_step: Largest change of any joint per grid step [rad], > 0.
        max_deviation: Largest deviation of any gripper point from its straight
            path [m], > 0.
        holding: The gripper holds the object (a retreat): the caller checks
            collisions with the object attached.
    """

    distance: float = 0.10
    direction: tuple[float, float, float] = (0.0, 0.0, -1.0)
    frame: str = "grasp"
    steps: int = 10
    max_joint_step: float = 0.25
    max_deviation: float = 0.002
    holding: bool = False

    def __post_init__(self) -> None:
        if not np.isfinite(self.distance) or self.distance < 0:
            raise InputError(f"move distance must be >= 0 [m], got {self.distance!r}")
        if int(self.steps) != self.steps or self.steps < 1:
            raise InputError(f"move steps must be an int >= 1, got {self.steps!r}")
        if not np.isfinite(self.max_joint_step) or self.max_joint_step <= 0:
            raise InputError(f"move max_joint_step must be > 0 [rad], got {self.max_joint_step!r}")
        if not np.isfinite(self.max_deviation) or self.max_deviation <= 0:
            raise InputError(f"move max_deviation must be > 0 [m], got {self.max_deviation!r}")
        if self.frame not in ("grasp", "base"):
            raise InputError(f"move frame must be 'grasp' or 'base', got {self.frame!r}")
        u = np.asarray(self.direction, dtype=float)
        if u.shape != (3,) or not np.all(np.isfinite(u)) or not np.any(u):
            raise InputError(f"move direction must be a non-zero 3-vector, got {self.direction!r}")
        u = u / np.abs(u).max()  # first: the norm of [1e300, 1e300, 1e300] overflows
        object.__setattr__(self, "direction", tuple((u / np.linalg.norm(u)).tolist()))
        object.__setattr__(self, "steps", int(self.steps))

    def offsets(self, poses: np.ndarray) -> np.ndarray:
        """Displacement :math:`d` (M, 3) [m] of each grasp pose (M, 4, 4), base frame."""
        u = np.asarray(self.direction)
        if self.frame == "grasp":
            return self.distance * (poses[:, :3, :3] @ u)
        return np.broadcast_to(self.distance * u, (poses.shape[0], 3)).copy()


class MovePlan(NamedTuple):
    """Kinematics of N moves (:func:`~gcm_pipeline.reach.path.plan_moves`).

    Attributes:
        ok: (N,) bool, the joint path exists within the bounds.
        reason: (N,) str, ``''`` or one of :data:`MOVE_REASONS`.
        failed_step: (N,) int, grid step 1..steps where tracking failed, 0 if ok.
        q_path: (N, steps + 1, nq) [rad] joint path at the grid points (index 0
            is the grasp); NaN rows where not ok.
        deviation: (N,) bound of the gripper's deviation from its line [m] (NaN if not ok).
        waypoints: (N,) int, IK waypoints solved after the grasp.
        knots: (N, steps * substeps + 1, nq) [rad] the IK waypoints on the fine
            grid ``s = j / (steps * substeps)``, NaN between them: the move is the
            piecewise linear joint path through them (``q_path`` samples it).
            None where the caller did not ask for them (``knots=False``).
    """

    ok: np.ndarray
    reason: np.ndarray
    failed_step: np.ndarray
    q_path: np.ndarray
    deviation: np.ndarray
    waypoints: np.ndarray
    knots: np.ndarray | None


class MoveResult(NamedTuple):
    """Kinematics and collisions of N moves (:func:`~gcm_pipeline.reach.move_check.check_moves`).

    Attributes:
        ok: (N,) bool, the move is followable and collision-free at every grid point.
        reason: (N,) str, ``''``, one of :data:`MOVE_REASONS` or a collision reason.
        failed_step: (N,) int, first failing grid step (1..steps), 0 if ok.
        q_end: (N, nq) [rad] configuration at the end of the move (the
            pre-grasp of an approach), NaN where not ok.
        q_path: (N, steps + 1, nq) joint path at the grid points (NaN where not ok).
        deviation: (N,) deviation bound [m] (NaN where not ok).
        knots: The IK waypoints (see :class:`MovePlan`), NaN where not ok; None
            where the caller did not ask for them (``knots=False``).
    """

    ok: np.ndarray
    reason: np.ndarray
    failed_step: np.ndarray
    q_end: np.ndarray
    q_path: np.ndarray
    deviation: np.ndarray
    knots: np.ndarray | None


def move_poses(poses: np.ndarray, offsets: np.ndarray, steps: int) -> np.ndarray:
    """Grasp-frame poses at the grid points of moves.

    Args:
        poses: Grasp poses (N, 4, 4) [m].
        offsets: Displacements (N, 3) [m] (see :meth:`Move.offsets`).
        steps: Grid steps, >= 1.

    Returns:
        (steps + 1, N, 4, 4): index 0 is the grasp, ``steps`` the end of the move.
    """
    poses = np.asarray(poses, dtype=float)
    frac = np.arange(steps + 1) / steps
    out = np.broadcast_to(poses, (steps + 1, *poses.shape)).copy()
    out[..., :3, 3] += frac[:, None, None] * offsets[None]
    return out


def unreachable_ends(
    robot: Robot,
    poses: np.ndarray,
    move: Move,
    position_tolerance: float,
    orientation_tolerance: float,
) -> np.ndarray:
    """Moves whose end no configuration reaches within the IK tolerances, (N,) bool.

    A proof, not a search: for the Panda's kinematics the end lies beyond what
    the elbow's limits let the arm reach, whatever joint 7 is
    (:meth:`~gcm_pipeline.robot.ik.panda.PandaAnalyticIK.unreachable`); for a
    6R arm of the UR geometry the links between the parallel axes are too
    short for the end's wrist point on every branch
    (:meth:`~gcm_pipeline.robot.ik.reach_6r.SixRReach.unreachable`). Such a
    move fails whatever configuration it starts from. All False for any other
    robot.

    Args:
        robot: The robot.
        poses: Grasp poses (N, 4, 4) in the base frame [m].
        move: The move.
        position_tolerance: IK tolerance of the end of the move [m].
        orientation_tolerance: IK tolerance [rad].
    """
    tg = np.asarray(poses, dtype=float).reshape(-1, 4, 4)
    solver = analytic_solver(robot)
    reach = six_r_reach(robot) if solver is None else None
    if (solver is None and reach is None) or move.distance == 0 or tg.shape[0] == 0:
        return np.zeros(tg.shape[0], dtype=bool)
    rot, end = tg[:, :3, :3], tg[:, :3, 3] + move.offsets(tg)
    with np.errstate(invalid="ignore"):
        if solver is not None:
            elbow = (robot.lower[3], robot.upper[3])
            out = solver.unreachable(rot, end, position_tolerance, orientation_tolerance, elbow)
        else:
            assert reach is not None
            out = reach.unreachable(rot, end, position_tolerance, orientation_tolerance)
    return out & np.all(np.isfinite(tg), axis=(1, 2))
