"""Reachability stage: inverse kinematics for every grasp of the table.

Reads ``dq`` (world poses of the grasp frame) and, when present, the
provenance columns ``origin``, ``vertices``, ``weights`` written by densify;
adds ``reachable``, ``reason``, ``q``, ``pos_err`` and ``rot_err``.

Targets in the robot base frame are ``inv(base_pose) @ T_world``. Candidate
rows are solved first; interpolated rows are then seeded from the solutions
of their triangle's vertices, heaviest weight first (nearby poses have nearby
configurations, so the warm start usually converges in a few iterations),
and fall back to the backend's usual seeds.

Reasons (``''`` when reachable): ``out_of_reach`` (farther from the shoulder
than the arm's maximum reach, a cheap pre-filter), ``joint_limits``,
``no_ik``, ``verification_failed`` and whatever a ``validator`` returns.

Collisions: with an ``environment`` or ``object_cfg`` section (or a
prebuilt ``checker``), "reachable" means an IK solution whose configuration
is collision-free and, with an ``approach`` section, whose straight-line
pre-grasp approach is followable and collision-free. The collision checker
(:func:`gcm_pipeline.stages.collision.make_checker`) is given to the IK as
validator, so a grasp whose first solution collides keeps trying other
seeds; the solutions are then filtered, their approach checked and their
``clearance`` added (:func:`gcm_pipeline.stages.collision.apply_collision_checks`).
Further reasons: ``collision_self``, ``collision_environment``,
``collision_object`` and ``approach``. Without these sections the stage is
pure IK.

Any other ``validator``, a callable ``q (M, nq) -> (M,) str`` (``''`` =
valid, else a reason), is applied by the IK to every converged candidate
before one is chosen (after the collision checker, when there is one), and a
grasp with no valid solution gets the validator's reason.
``return_candidates=True`` also returns every converged IK candidate (valid
or not) as :class:`IKCandidates`, with row ids into the table.
"""

from __future__ import annotations

import logging
from typing import TYPE_CHECKING, Any

import numpy as np

from gcm_pipeline.errors import InputError
from gcm_pipeline.robot.ik import IKCandidates, Validator, solve_ik, world_to_base_targets
from gcm_pipeline.robot.model import Robot, load_robot
from gcm_pipeline.stages import collision
from gcm_pipeline.table import GraspTable

if TYPE_CHECKING:
    from gcm_pipeline.config import ApproachConfig, EnvironmentConfig, ObjectConfig, Pose
    from gcm_pipeline.robot.collision import CollisionChecker

__all__ = ["check_reachability", "world_to_base_targets"]


def _combined_validator(
    checker: CollisionChecker | None, validator: Validator | None
) -> Validator | None:
    """The collision checker's reasons first, then those of ``validator``."""
    if checker is None:
        return validator
    if validator is None:
        return checker.check
    extra = validator

    def check(q: np.ndarray) -> np.ndarray:
        reason = np.asarray(checker.check(q), dtype=object)
        free = np.flatnonzero(reason == "")
        if free.size:
            reason[free] = np.asarray(extra(q[free]), dtype=object)
        return reason.astype(str)

    return check


def _neighbours(grasps: GraspTable) -> np.ndarray | None:
    """Warm-start rows (N, 3) from provenance: vertices by decreasing weight."""
    if "vertices" not in grasps:
        return None
    n = len(grasps)
    vert = np.asarray(grasps["vertices"])
    if vert.ndim != 2 or not np.issubdtype(vert.dtype, np.integer):
        raise InputError(f"grasp column 'vertices' must be an int array (N, K), got {vert.dtype}")
    vert = vert.astype(int)
    bad = (vert < -1) | (vert >= n)
    if np.any(bad):
        i = int(np.flatnonzero(bad.any(axis=1))[0])
        raise InputError(
            f"grasp column 'vertices' row {i} has row ids {vert[i].tolist()} outside [-1, {n - 1}]"
        )
    if "origin" in grasps:
        is_candidate = np.asarray(grasps["origin"]).astype(str) == "candidate"
        vert = np.where(is_candidate[:, None], -1, vert)
    if "weights" in grasps:
        w = np.asarray(grasps["weights"], dtype=float)
        if w.shape == vert.shape:
            order = np.argsort(-np.nan_to_num(w, nan=-np.inf), axis=1, kind="stable")
            vert = np.take_along_axis(vert, order, axis=1)
    # a row never seeds itself
    vert = np.where(vert == np.arange(n)[:, None], -1, vert)
    return vert


def check_reachability(
    grasps: GraspTable,
    robot: Robot | str,
    *,
    base_pose: Pose | np.ndarray | None = None,
    backend: str = "pinocchio",
    position_tolerance: float = 1e-4,
    orientation_tolerance: float = 1e-3,
    progress: bool = False,
    validator: Validator | None = None,
    workers: int = 1,
    seed: int | None = None,
    warm_start: bool = True,
    return_candidates: bool = False,
    environment: EnvironmentConfig | None = None,
    object_cfg: ObjectConfig | None = None,
    approach: ApproachConfig | None = None,
    checker: CollisionChecker | None = None,
    **options: Any,
) -> GraspTable | tuple[GraspTable, IKCandidates]:
    """Solve IK for every grasp, check collisions and approach, add the reachability columns.

    Args:
        grasps: Table with ``dq`` (N, 8) (world poses of the grasp frame) and
            optionally ``origin``, ``vertices``, ``weights`` (provenance).
        robot: A :class:`Robot` or a spec name/path.
        base_pose: Robot base in the world, a config ``Pose`` or (4, 4) [m];
            identity if None.
        backend: IK backend, ``"pinocchio"`` or ``"mink"``.
        position_tolerance: [m], > 0.
        orientation_tolerance: [rad], > 0.
        progress: Log a one-line summary (the IK is batched, so there is no
            per-grasp progress to show).
        validator: Optional ``q (M, nq) -> (M,) str`` ('' = valid) applied to
            converged IK candidates (see the module docstring).
        workers: Processes for the IK (0 = all cores).
        seed: Random seed of the IK's seed library and restarts.
        warm_start: Seed interpolated rows from their vertices' solutions.
        return_candidates: Also return every converged IK candidate.
        environment: The ``environment`` config section (collision world).
        object_cfg: The ``object`` config section (the object to grasp).
        approach: The ``approach`` config section (pre-grasp approach check).
        checker: A prebuilt
            :class:`~gcm_pipeline.robot.collision.CollisionChecker`; else one
            is built from ``environment`` and ``object_cfg`` when either is given.
        **options: Backend options (see :func:`~gcm_pipeline.robot.ik.solve_ik`).

    Returns:
        The table with ``reachable`` (N,) bool, ``reason`` (N,) str, ``q``
        (N, nq) [rad] (NaN rows when unreachable), ``pos_err`` [m] and
        ``rot_err`` [rad] added, and ``clearance`` [m] when collisions are
        checked; with ``return_candidates``, a pair ``(table, candidates)``
        (the IK candidates before the collision filter).

    Raises:
        InputError: Missing ``dq`` column, bad provenance, bad options.
        GeometryError: Non-unit dual quaternions or a non-rigid base pose.
    """
    robot = load_robot(robot)
    if "dq" not in grasps:
        raise InputError(f"grasp table has no column 'dq'; columns: {', '.join(grasps.columns)}")
    targets = world_to_base_targets(grasps["dq"], base_pose)
    nb = _neighbours(grasps) if warm_start else None
    if seed is not None:
        options.setdefault("random_seed", int(seed))
    if checker is None and (environment is not None or object_cfg is not None):
        checker = collision.make_checker(robot, environment, object_cfg, base_pose)
    res = solve_ik(
        robot,
        targets,
        backend,
        position_tolerance=position_tolerance,
        orientation_tolerance=orientation_tolerance,
        neighbours=nb,
        validator=_combined_validator(checker, validator),
        return_all=return_candidates,
        workers=workers,
        **options,
    )
    if progress:
        logging.getLogger(__name__).info("reachability: %r", res)
    table = grasps.with_columns(
        reachable=res.success,
        reason=res.reason,
        q=res.q,
        pos_err=res.pos_err,
        rot_err=res.rot_err,
    )
    ik: dict[str, Any] = {
        "base_pose": base_pose,
        "backend": backend,
        "position_tolerance": position_tolerance,
        "orientation_tolerance": orientation_tolerance,
    }
    if checker is not None:
        table = collision.apply_collision_checks(
            table,
            robot,
            environment=environment,
            object_cfg=object_cfg,
            approach=approach,
            checker=checker,
            **ik,
        )
    elif approach is not None:
        table = collision.check_approach(table, robot, None, approach, **ik)
    if return_candidates:
        assert res.candidates is not None
        return table, res.candidates
    return table
