"""Pre-grasp approach check: the straight line from the pre-grasp to the grasp.

The pre-grasp is the grasp frame backed off along its approach axis (its z)::

    T_pre = T_grasp @ translate(0, 0, -distance)

The hand must be able to move from ``T_pre`` to ``T_grasp`` along the straight
line, with the grasp frame's orientation fixed. The line is cut into ``steps``
equal segments and tracked by IK *from the grasp solution backwards* (the path
is the same either way; starting from the configuration that reaches the grasp
keeps the approach on that IK branch): waypoint ``k`` is solved by
:func:`~gcm_pipeline.robot.ik.solve_ik` seeded with waypoint ``k - 1``'s
solution, for all grasps at once, one step after the other. A grasp passes when
at every waypoint

* the IK converges (within the IK tolerances, inside the joint limits),
* no joint moves more than ``max_joint_step`` [rad] from the previous waypoint
  (a jump means the IK left the branch, the motion would not be a short
  straight move), and
* the configuration is collision-free. Waypoints before the grasp are checked
  with ``path_checker`` (by default the same world with **no** contact
  tolerance at the fingers: only the final grasp may touch the object within
  ``contact_tolerance``; that final configuration is the caller's grasp
  solution and is not re-checked here).

Only the seed given and the home configuration are tried at each waypoint (no
random restarts): a waypoint reached only from elsewhere would fail the joint
step bound anyway.
"""

from __future__ import annotations

from typing import Any, NamedTuple

import numpy as np

from gcm_pipeline.errors import InputError
from gcm_pipeline.robot.ik import solve_ik
from gcm_pipeline.robot.model import Robot

__all__ = ["ApproachResult", "approach_waypoints", "check_approach_path"]


class ApproachResult(NamedTuple):
    """Result of :func:`check_approach_path` for N grasps.

    Attributes:
        ok: (N,) bool, True if the whole approach is followable and collision-free.
        reason: (N,) str, ``''`` or why the approach fails: ``no_ik`` (a waypoint
            has no IK solution near the previous one), ``joint_step`` (a joint
            jumps more than ``max_joint_step``), ``collision_environment`` /
            ``collision_self`` / ``collision_object`` (a waypoint collides),
            ``invalid`` (no grasp configuration given).
        failed_step: (N,) int, waypoint index 1..steps where it failed (1 = next to
            the grasp, ``steps`` = pre-grasp), 0 if ok.
        q_pregrasp: (N, nq) [rad] configuration at the pre-grasp, NaN where not ok.
        max_joint_step: (N,) largest joint change between waypoints [rad] (NaN if none).
    """

    ok: np.ndarray
    reason: np.ndarray
    failed_step: np.ndarray
    q_pregrasp: np.ndarray
    max_joint_step: np.ndarray


def approach_waypoints(grasp_poses: np.ndarray, distance: float, steps: int) -> np.ndarray:
    """Grasp-frame poses along the approach, from the grasp back to the pre-grasp.

    Args:
        grasp_poses: Grasp poses (N, 4, 4) [m].
        distance: Back-off distance along the grasp frame's z [m], >= 0.
        steps: Number of segments, >= 1.

    Returns:
        (steps + 1, N, 4, 4): index 0 is the grasp, ``steps`` the pre-grasp
        ``T_grasp @ translate(0, 0, -distance)``.
    """
    poses = np.asarray(grasp_poses, dtype=float)
    offsets = -distance * np.arange(steps + 1) / steps  # (S+1,)
    out = np.broadcast_to(poses, (steps + 1, *poses.shape)).copy()
    out[..., :3, 3] = poses[None, :, :3, 3] + offsets[:, None, None] * poses[None, :, :3, 2]
    return out


def check_approach_path(
    robot: Robot,
    grasp_poses: Any,
    q_grasp: Any,
    path_checker: Any | None,
    *,
    distance: float = 0.10,
    steps: int = 10,
    max_joint_step: float = 0.25,
    position_tolerance: float = 1e-4,
    orientation_tolerance: float = 1e-3,
    backend: str = "pinocchio",
    **ik_options: Any,
) -> ApproachResult:
    """Check the straight-line approach of N grasps, batched over the grasps.

    Args:
        robot: The robot.
        grasp_poses: Grasp-frame poses (N, 4, 4) in the robot base frame [m].
        q_grasp: Configurations reaching them (N, nq) [rad]; NaN rows are skipped
            (reason ``invalid``).
        path_checker: Object with ``check(q (M, nq)) -> (M,) str`` for the
            waypoints (a :class:`~gcm_pipeline.robot.collision.CollisionChecker`),
            or None to skip collisions.
        distance: Approach distance [m], >= 0 (0: nothing to check, all pass).
        steps: Number of segments of the line, >= 1.
        max_joint_step: Largest change of any joint between waypoints [rad], > 0.
        position_tolerance: IK position tolerance [m].
        orientation_tolerance: IK orientation tolerance [rad].
        backend: IK backend for :func:`~gcm_pipeline.robot.ik.solve_ik`.
        **ik_options: Further backend options (the ``pinocchio`` backend gets
            ``library_seeds=0, random_restarts=0`` unless given).

    Returns:
        The :class:`ApproachResult`.

    Raises:
        InputError: Negative distance, steps < 1, max_joint_step <= 0, or arrays
            of the wrong shape.
    """
    poses = np.asarray(grasp_poses, dtype=float)
    if poses.ndim == 2:
        poses = poses[None]
    qg = np.asarray(q_grasp, dtype=float)
    if qg.ndim == 1:
        qg = qg[None]
    n, nq = poses.shape[0], robot.nq
    if poses.shape != (n, 4, 4) or qg.shape != (n, nq):
        raise InputError(
            f"grasp_poses must be (N, 4, 4) and q_grasp (N, {nq}) with the same N, "
            f"got {poses.shape} and {qg.shape}"
        )
    if not np.isfinite(distance) or distance < 0:
        raise InputError(f"approach distance must be >= 0 [m], got {distance!r}")
    if int(steps) != steps or steps < 1:
        raise InputError(f"approach steps must be an int >= 1, got {steps!r}")
    if not np.isfinite(max_joint_step) or max_joint_step <= 0:
        raise InputError(f"approach max_joint_step must be > 0 [rad], got {max_joint_step!r}")
    steps = int(steps)

    ok = np.all(np.isfinite(qg), axis=1) & np.all(np.isfinite(poses), axis=(1, 2))
    reason = np.where(ok, "", "invalid").astype(object)
    failed = np.zeros(n, dtype=int)
    biggest = np.full(n, np.nan)
    q_cur = qg.copy()
    q_cur[~ok] = np.nan
    if distance == 0 or not np.any(ok):
        return ApproachResult(
            ok, reason.astype(str), failed, np.where(ok[:, None], qg, np.nan), biggest
        )
    if backend == "pinocchio":
        ik_options = {"library_seeds": 0, "random_restarts": 0, **ik_options}
    biggest[ok] = 0.0
    waypoints = approach_waypoints(poses, distance, steps)
    for k in range(1, steps + 1):
        rows = np.flatnonzero(ok)
        if rows.size == 0:
            break
        res = solve_ik(
            robot,
            waypoints[k, rows],
            backend,
            position_tolerance=position_tolerance,
            orientation_tolerance=orientation_tolerance,
            seeds=q_cur[rows][:, None, :],
            **ik_options,
        )
        bad_ik = ~res.success
        jump = np.max(np.abs(np.where(bad_ik[:, None], 0.0, res.q - q_cur[rows])), axis=1)
        bad_step = ~bad_ik & (jump > max_joint_step)
        biggest[rows[~bad_ik]] = np.maximum(biggest[rows[~bad_ik]], jump[~bad_ik])
        coll = np.full(rows.size, "", dtype=object)
        fine = ~bad_ik & ~bad_step
        if path_checker is not None and np.any(fine):
            coll[fine] = np.asarray(path_checker.check(res.q[fine]), dtype=object)
        why = np.where(bad_ik, "no_ik", np.where(bad_step, "joint_step", coll))
        fail = why != ""
        reason[rows[fail]] = why[fail]
        failed[rows[fail]] = k
        ok[rows[fail]] = False
        q_cur[rows[~fail]] = res.q[~fail]
        q_cur[rows[fail]] = np.nan
    q_pre = np.where(ok[:, None], q_cur, np.nan)
    return ApproachResult(ok, reason.astype(str), failed, q_pre, biggest)
