"""Reachability of a grasp table: the engine run on its poses, its columns added.

Reads ``dq`` (world poses of the grasp frame) and, when present, the
provenance columns ``origin``, ``vertices``, ``weights`` written by densify;
adds ``reachable``, ``reason``, ``q``, ``pos_err``, ``rot_err``, the diagnostic
columns ``q_pregrasp``, ``q_retreat``, ``q_rejected`` and, with a collision
checker, ``clearance``.

The decision itself, IK, collisions, approach, retreat and re-solves, is made
in one place, :class:`gcm_pipeline.reach.engine.ReachabilityEngine` (its
module docstring states the sequence), configured by one
:class:`~gcm_pipeline.reach.options.ReachOptions` (:mod:`gcm_pipeline.pipeline`
maps a config onto it and onto the
:class:`~gcm_pipeline.robot.collision.CollisionChecker`). Here: targets in the
robot base frame are ``inv(base_pose) @ T_world``; interpolated rows are
seeded from the final solutions of their triangle's vertices, heaviest weight
first.

Reasons (``''`` when reachable): ``out_of_reach``, ``joint_limits``,
``no_ik``, ``verification_failed``, ``collision_self``,
``collision_environment``, ``collision_object``, a ``validator``'s reasons,
``approach`` and ``retreat``. Without a checker the check is pure IK.
"""

from __future__ import annotations

import logging
from typing import TYPE_CHECKING, Any

import numpy as np

from gcm_pipeline.errors import InputError
from gcm_pipeline.progress import Reporter
from gcm_pipeline.reach.engine import ReachabilityEngine
from gcm_pipeline.reach.options import ReachOptions
from gcm_pipeline.robot.ik import IKCandidates, Validator, world_to_base_targets
from gcm_pipeline.robot.model import Robot, RobotSpec, as_robot
from gcm_pipeline.table import GraspTable

if TYPE_CHECKING:
    from gcm_pipeline.robot.collision import CollisionChecker

__all__ = [
    "check_reachability",
    "make_engine",
    "world_to_base_targets",
]

log = logging.getLogger(__name__)


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


def make_engine(
    robot: Robot | RobotSpec,
    options: ReachOptions | None = None,
    *,
    checker: CollisionChecker | None = None,
    validator: Validator | None = None,
) -> ReachabilityEngine:
    """The reachability engine of these options (build once, run many times).

    Args:
        robot: A :class:`Robot` or a spec name/path.
        options: The :class:`ReachOptions` (None: the defaults).
        checker: A :class:`~gcm_pipeline.robot.collision.CollisionChecker`
            (None: no collision checks, pure IK).
        validator: Optional ``q (M, nq) -> (M,) str`` ('' = valid), an extra
            check of grasp configurations after the collision check.

    Returns:
        The :class:`~gcm_pipeline.reach.engine.ReachabilityEngine`; call its
        ``close()`` (or use it in a ``with`` block) to stop its worker processes.
    """
    robot = as_robot(robot)
    opt = ReachOptions() if options is None else options
    ik_options = dict(opt.ik_options)
    if opt.seed is not None:
        ik_options.setdefault("random_seed", int(opt.seed))
    return ReachabilityEngine(
        robot,
        checker,
        backend=opt.backend,
        position_tolerance=opt.position_tolerance,
        orientation_tolerance=opt.orientation_tolerance,
        approach=opt.approach,
        retreat=opt.retreat,
        validator=validator,
        alternatives=opt.alternatives,
        workers="auto" if opt.workers in (0, "auto") else opt.workers,
        chunk_size=opt.chunk_size,
        ik_options=ik_options,
        solutions=opt.solutions,
    )


def check_reachability(
    grasps: GraspTable,
    robot: Robot | RobotSpec,
    options: ReachOptions | None = None,
    *,
    checker: CollisionChecker | None = None,
    validator: Validator | None = None,
    engine: ReachabilityEngine | None = None,
    seeds: Any = None,
    progress: bool = False,
    return_candidates: bool = False,
) -> GraspTable | tuple[GraspTable, IKCandidates]:
    """Solve IK for every grasp, check collisions, approach and retreat; add the columns.

    Args:
        grasps: Table with ``dq`` (N, 8) (world poses of the grasp frame) and
            optionally ``origin``, ``vertices``, ``weights`` (provenance).
        robot: A :class:`Robot` or a :class:`RobotSpec`.
        options: The :class:`ReachOptions` (None: the defaults); with
            ``engine``, only its ``base_pose`` and ``warm_start`` are used.
        checker: A :class:`~gcm_pipeline.robot.collision.CollisionChecker`
            in the base frame (None: no collision checks, pure IK).
        validator: Optional ``q (M, nq) -> (M,) str`` ('' = valid), an extra
            check of grasp configurations after the collision check.
        engine: A prebuilt engine (:func:`make_engine`, reused across calls);
            ``checker`` and ``validator`` are then ignored.
        seeds: Optional warm starts (N, K, nq) [rad], tried after the vertices'.
        progress: Report per-target progress (a bar on a terminal, else a log
            line every few seconds; see :class:`~gcm_pipeline.progress.Reporter`).
        return_candidates: Also return every converged IK candidate of the
            first solve (before any check).

    Returns:
        The table with ``reachable`` (N,) bool, ``reason`` (N,) str, ``q``
        (N, nq) [rad] (NaN rows when unreachable), ``pos_err`` [m],
        ``rot_err`` [rad], ``q_pregrasp``, ``q_retreat``, ``q_rejected`` (N, nq)
        and ``clearance`` [m] when collisions are checked; when the engine
        keeps several branches, also ``solutions`` (N, K, nq),
        ``solutions_q_pregrasp``, ``solutions_q_retreat`` (N, K, nq),
        ``solutions_clearance`` (N, K) and ``n_solutions`` (N,) (branch 0 is
        ``q``); with ``return_candidates``, a pair ``(table, candidates)``.

    Raises:
        InputError: Missing ``dq`` column, bad provenance, bad options.
        GeometryError: Non-unit dual quaternions or a non-rigid base pose.
    """
    opt = ReachOptions() if options is None else options
    robot = as_robot(robot)
    if "dq" not in grasps:
        raise InputError(f"grasp table has no column 'dq'; columns: {', '.join(grasps.columns)}")
    targets = world_to_base_targets(grasps["dq"], opt.base_pose)
    nb = _neighbours(grasps) if opt.warm_start else None
    own = engine is None
    if engine is None:
        engine = make_engine(robot, opt, checker=checker, validator=validator)
    report = Reporter(len(grasps), enabled=progress, desc="reachability", unit="pose")
    try:
        res = engine.run(
            targets,
            neighbours=nb,
            seeds=seeds,
            progress=report,
            return_candidates=return_candidates,
        )
    finally:
        report.close()
        if own:
            engine.close()
    log.debug("reachability: %r", res)
    columns: dict[str, Any] = {
        "reachable": res.reachable,
        "reason": res.reason,
        "q": res.q,
        "pos_err": res.pos_err,
        "rot_err": res.rot_err,
        "q_pregrasp": res.q_pregrasp,
        "q_retreat": res.q_retreat,
        "q_rejected": res.q_rejected,
    }
    if res.clearance is not None:
        columns["clearance"] = res.clearance
    if res.branches is not None:
        b = res.branches
        columns.update(
            solutions=b.q,
            solutions_q_pregrasp=b.q_pregrasp,
            solutions_q_retreat=b.q_retreat,
            n_solutions=b.count,
        )
        if b.clearance is not None:
            columns["solutions_clearance"] = b.clearance
    table = grasps.with_columns(**columns)
    if return_candidates:
        assert res.candidates is not None
        return table, res.candidates
    return table
