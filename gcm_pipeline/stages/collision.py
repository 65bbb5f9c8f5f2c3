"""Collision and approach checks of the reachability columns, clearance and combined score.

"Reachable means collision-free": after IK, a grasp stays ``reachable`` only if
its configuration is collision-free (self, environment, object; see
:mod:`gcm_pipeline.robot.collision`) and, with an ``approach`` section, its
pre-grasp approach is followable and collision-free (see
:mod:`gcm_pipeline.robot.approach`). The functions here post-process a grasp
table that has the reachability columns ``reachable, reason, q, pos_err,
rot_err``:

* :func:`filter_collisions` checks the solutions; a colliding row is re-solved
  with :func:`~gcm_pipeline.robot.ik.solve_ik` from other seeds with the
  checker as validator (other IK branches), and keeps its collision reason
  (``collision_self``, ``collision_environment``, ``collision_object``) only if
  none is collision-free;
* :func:`check_approach` checks the approach of the reachable rows; a failing
  row tries the other collision-free IK solutions of its grasp before it gets
  reason ``approach``;
* :func:`add_clearance` adds the ``clearance`` column [m];
* :func:`apply_collision_checks` does all three from the config sections
  (one call for the reachability stage);
* :func:`combined_score` is the ``combined`` ranking metric.

Unreachable rows have NaN ``q`` (as :class:`~gcm_pipeline.robot.ik.IKResult`
does) and keep the ``pos_err`` / ``rot_err`` of their IK solution.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np

from gcm_pipeline.config import ApproachConfig, EnvironmentConfig, ObjectConfig, Pose
from gcm_pipeline.errors import ConfigError, InputError, unknown_choice
from gcm_pipeline.robot.approach import check_approach_path
from gcm_pipeline.robot.collision import (
    REASON_ENVIRONMENT,
    REASON_OBJECT,
    REASON_SELF,
    CollisionChecker,
)
from gcm_pipeline.robot.ik import solve_ik, verify_solutions, world_to_base_targets
from gcm_pipeline.robot.model import Robot
from gcm_pipeline.table import GraspTable

__all__ = [
    "COLLISION_REASONS",
    "DEFAULT_COMBINED_WEIGHTS",
    "REASON_APPROACH",
    "add_clearance",
    "apply_collision_checks",
    "check_approach",
    "combined_score",
    "filter_collisions",
    "grasp_targets",
    "make_checker",
]

REASON_APPROACH = "approach"
COLLISION_REASONS = (REASON_SELF, REASON_ENVIRONMENT, REASON_OBJECT)

#: Weights of the ``combined`` metric when the config gives none.
DEFAULT_COMBINED_WEIGHTS: dict[str, float] = {
    "yoshikawa": 1.0,
    "clearance": 0.5,
    "joint_limit_margin": 0.2,
}

#: Extra seeds for re-solving colliding rows (pinocchio backend options).
_RESOLVE_OPTIONS = {"library_seeds": 24, "random_restarts": 16}


def make_checker(
    robot: Robot,
    environment: EnvironmentConfig | None = None,
    object_cfg: ObjectConfig | None = None,
    base_pose: Pose | np.ndarray | None = None,
    *,
    threads: int = 1,
) -> CollisionChecker:
    """The collision checker of a run (``environment``, ``object``, ``robot.base_pose``).

    Args:
        robot: The robot.
        environment: Config section (None: the default, a table at z = 0).
        object_cfg: Config ``object`` section or None.
        base_pose: Robot base in the world (Pose or (4, 4)); None: identity.
        threads: Threads for the batched checks.

    Returns:
        The :class:`~gcm_pipeline.robot.collision.CollisionChecker`.
    """
    return CollisionChecker(robot, environment, object_cfg, base_pose, threads=threads)


def grasp_targets(grasps: GraspTable, base_pose: Pose | np.ndarray | None = None) -> np.ndarray:
    """Grasp-frame poses of the table in the robot base frame, (N, 4, 4) [m].

    See :func:`~gcm_pipeline.robot.ik.world_to_base_targets`.
    """
    return world_to_base_targets(grasps["dq"], base_pose)


def _need(grasps: GraspTable, names: tuple[str, ...]) -> None:
    missing = [c for c in names if c not in grasps]
    if missing:
        raise InputError(
            f"grasp table lacks column(s) {', '.join(missing)} (run the reachability stage "
            f"first); columns: {', '.join(grasps.columns)}"
        )


_REACH_COLS = ("dq", "reachable", "reason", "q", "pos_err", "rot_err")


def filter_collisions(
    grasps: GraspTable,
    robot: Robot,
    checker: CollisionChecker,
    *,
    base_pose: Pose | np.ndarray | None = None,
    backend: str = "pinocchio",
    position_tolerance: float = 1e-4,
    orientation_tolerance: float = 1e-3,
    resolve: bool = True,
    **ik_options: Any,
) -> GraspTable:
    """Keep ``reachable`` only for collision-free solutions; re-solve colliding rows.

    Args:
        grasps: Table with ``dq, reachable, reason, q, pos_err, rot_err``.
        robot: The robot.
        checker: The collision checker of the run.
        base_pose: Robot base in the world.
        backend: IK backend for re-solving.
        position_tolerance: IK tolerance [m].
        orientation_tolerance: IK tolerance [rad].
        resolve: Re-solve colliding rows from other seeds (else just reject them).
        **ik_options: Options for :func:`~gcm_pipeline.robot.ik.solve_ik`; the
            pinocchio backend gets more seeds than usual unless given.

    Returns:
        The table with ``reachable, reason, q, pos_err, rot_err`` updated.
    """
    _need(grasps, _REACH_COLS)
    reachable = np.array(grasps["reachable"], dtype=bool)
    reason = np.array(grasps["reason"], dtype=object)
    q = np.array(grasps["q"], dtype=float)
    pos_err = np.array(grasps["pos_err"], dtype=float)
    rot_err = np.array(grasps["rot_err"], dtype=float)
    rows = np.flatnonzero(reachable)
    why = checker.check(q[rows]) if rows.size else np.zeros(0, dtype=str)
    bad = rows[why != ""]
    if bad.size == 0:
        return grasps
    reason[bad] = why[why != ""]
    reachable[bad] = False
    q[bad] = np.nan
    if resolve:
        opts = dict(_RESOLVE_OPTIONS, **ik_options) if backend == "pinocchio" else ik_options
        res = solve_ik(
            robot,
            grasp_targets(grasps.take(bad), base_pose),
            backend,
            position_tolerance=position_tolerance,
            orientation_tolerance=orientation_tolerance,
            validator=checker.check,
            **opts,
        )
        ok = res.success
        reachable[bad[ok]] = True
        reason[bad[ok]] = ""
        q[bad[ok]] = res.q[ok]
        pos_err[bad[ok]] = res.pos_err[ok]
        rot_err[bad[ok]] = res.rot_err[ok]
        # a row still failing keeps its collision reason unless the re-solve found
        # another collision (e.g. self instead of environment on another branch)
        other = ~ok & np.isin(res.reason, COLLISION_REASONS)
        reason[bad[other]] = res.reason[other]
    return grasps.with_columns(
        reachable=reachable,
        reason=reason.astype(str),
        q=q,
        pos_err=pos_err,
        rot_err=rot_err,
    )


def check_approach(
    grasps: GraspTable,
    robot: Robot,
    checker: CollisionChecker | None,
    approach: ApproachConfig | None,
    *,
    base_pose: Pose | np.ndarray | None = None,
    backend: str = "pinocchio",
    position_tolerance: float = 1e-4,
    orientation_tolerance: float = 1e-3,
    alternatives: int = 4,
    **ik_options: Any,
) -> GraspTable:
    """Reject reachable grasps whose pre-grasp approach fails (reason ``approach``).

    The approach of a reachable row starts from its solution ``q``. When it
    fails, up to ``alternatives`` other collision-free IK solutions of the
    grasp are tried (from other seeds); the first whose approach passes
    replaces ``q``. The waypoints before the grasp are checked with no
    finger-contact tolerance (only the grasp itself may touch the object
    within ``contact_tolerance``).

    Args:
        grasps: Table with the reachability columns.
        robot: The robot.
        checker: The run's collision checker (None: no collision checks on the path).
        approach: The ``approach`` config section; None returns ``grasps`` unchanged.
        base_pose: Robot base in the world.
        backend: IK backend.
        position_tolerance: IK tolerance [m].
        orientation_tolerance: IK tolerance [rad].
        alternatives: Other IK solutions tried per failing grasp (0: none).
        **ik_options: Options for :func:`~gcm_pipeline.robot.ik.solve_ik` (path tracking).

    Returns:
        The table with ``reachable, reason, q, pos_err, rot_err`` updated.
    """
    if approach is None:
        return grasps
    _need(grasps, _REACH_COLS)
    reachable = np.array(grasps["reachable"], dtype=bool)
    rows = np.flatnonzero(reachable)
    if rows.size == 0 or approach.distance == 0:
        return grasps
    reason = np.array(grasps["reason"], dtype=object)
    q = np.array(grasps["q"], dtype=float)
    pos_err = np.array(grasps["pos_err"], dtype=float)
    rot_err = np.array(grasps["rot_err"], dtype=float)
    targets = grasp_targets(grasps.take(rows), base_pose)
    path_checker = None
    if checker is not None:
        path_checker = checker.with_contact_tolerance(0.0) if checker.contact_tolerance else checker
    kw = dict(
        distance=approach.distance,
        steps=approach.steps,
        max_joint_step=approach.max_joint_step,
        position_tolerance=position_tolerance,
        orientation_tolerance=orientation_tolerance,
        backend=backend,
        **ik_options,
    )
    res = check_approach_path(robot, targets, q[rows], path_checker, **kw)
    fail = np.flatnonzero(~res.ok)
    if fail.size and alternatives > 0:
        fixed = _alternative_approaches(
            robot, targets[fail], q[rows[fail]], checker, path_checker, alternatives, kw
        )
        for i, qa in fixed.items():
            row = rows[fail[i]]
            q[row] = qa
        if fixed:
            changed = np.array([rows[fail[i]] for i in fixed])
            pe, re, _ = verify_solutions(
                robot, q[changed], grasp_targets(grasps.take(changed), base_pose)
            )
            pos_err[changed], rot_err[changed] = pe, re
        keep = np.ones(fail.size, dtype=bool)
        keep[list(fixed)] = False  # ``fixed`` is keyed by position in ``fail``
        fail = fail[keep]
    bad = rows[fail]
    reachable[bad] = False
    reason[bad] = REASON_APPROACH
    q[bad] = np.nan
    return grasps.with_columns(
        reachable=reachable,
        reason=reason.astype(str),
        q=q,
        pos_err=pos_err,
        rot_err=rot_err,
    )


def _alternative_approaches(
    robot: Robot,
    targets: np.ndarray,
    q_first: np.ndarray,
    checker: CollisionChecker | None,
    path_checker: Any,
    alternatives: int,
    kw: dict[str, Any],
) -> dict[int, np.ndarray]:
    """Other valid IK solutions of failing grasps whose approach passes: {index: q}."""
    backend = kw["backend"]
    opts: dict[str, Any] = {}
    if backend == "pinocchio":
        opts = {
            "min_solutions": alternatives + 1,
            "first_round_seeds": alternatives + 1,
            "round_seeds": alternatives + 1,
            "library_seeds": 3 * (alternatives + 1),
            "random_restarts": 0,
        }
    res = solve_ik(
        robot,
        targets,
        backend,
        position_tolerance=kw["position_tolerance"],
        orientation_tolerance=kw["orientation_tolerance"],
        validator=None if checker is None else checker.check,
        return_all=True,
        **opts,
    )
    cand = res.candidates
    if cand is None or len(cand.index) == 0:
        return {}
    valid = cand.reason == ""
    idx, cq = cand.index[valid], cand.q[valid]
    # drop the solution already tried (same branch) and keep a few per grasp
    same = np.max(np.abs(cq - q_first[idx]), axis=1) < 1e-3
    idx, cq = idx[~same], cq[~same]
    order = np.argsort(idx, kind="stable")
    idx, cq = idx[order], cq[order]
    rank_in_group = np.arange(len(idx)) - np.searchsorted(idx, idx, side="left")
    keep = rank_in_group < alternatives
    idx, cq = idx[keep], cq[keep]
    if len(idx) == 0:
        return {}
    path = check_approach_path(robot, targets[idx], cq, path_checker, **kw)
    out: dict[int, np.ndarray] = {}
    for i, qa, ok in zip(idx.tolist(), cq, path.ok, strict=True):
        if ok and i not in out:
            out[i] = qa
    return out


def add_clearance(grasps: GraspTable, checker: CollisionChecker) -> GraspTable:
    """Add ``clearance`` (N,) [m]: distance of the arm to environment and object.

    See :meth:`~gcm_pipeline.robot.collision.CollisionChecker.clearance` (the
    gripper vs the object is left out). NaN for unreachable rows.
    """
    _need(grasps, ("reachable", "q"))
    out = np.full(len(grasps), np.nan)
    rows = np.flatnonzero(np.asarray(grasps["reachable"], dtype=bool))
    if rows.size:
        out[rows] = checker.clearance(np.asarray(grasps["q"], dtype=float)[rows])
    return grasps.with_columns(clearance=out)


def apply_collision_checks(
    grasps: GraspTable,
    robot: Robot,
    *,
    environment: EnvironmentConfig | None = None,
    object_cfg: ObjectConfig | None = None,
    approach: ApproachConfig | None = None,
    base_pose: Pose | np.ndarray | None = None,
    backend: str = "pinocchio",
    position_tolerance: float = 1e-4,
    orientation_tolerance: float = 1e-3,
    checker: CollisionChecker | None = None,
    threads: int = 1,
) -> GraspTable:
    """Collision filter, approach check and clearance in one call.

    Args:
        grasps: Table with the reachability columns.
        robot: The robot.
        environment: ``environment`` config section.
        object_cfg: ``object`` config section or None.
        approach: ``approach`` config section or None (no approach check).
        base_pose: Robot base in the world.
        backend: IK backend.
        position_tolerance: IK tolerance [m].
        orientation_tolerance: IK tolerance [rad].
        checker: A checker already built (e.g. the one given to ``solve_ik`` as
            validator); else built from the sections.
        threads: Threads for the batched collision checks.

    Returns:
        The table with the reachability columns updated and ``clearance`` added.
    """
    if checker is None:
        checker = make_checker(robot, environment, object_cfg, base_pose, threads=threads)
    ik: dict[str, Any] = dict(
        base_pose=base_pose,
        backend=backend,
        position_tolerance=position_tolerance,
        orientation_tolerance=orientation_tolerance,
    )
    grasps = filter_collisions(grasps, robot, checker, **ik)
    grasps = check_approach(grasps, robot, checker, approach, **ik)
    return add_clearance(grasps, checker)


def combined_score(
    columns: Mapping[str, Any],
    weights: Mapping[str, float] | None = None,
    *,
    mask: Any = None,
    normalization: str = "minmax",
) -> np.ndarray:
    r"""Weighted combination of ranking metrics, each normalised to [0, 1].

    .. math::

        s_i = \sum_m \frac{w_m}{\sum_k w_k} \, \hat{x}_{m,i}, \qquad
        \hat{x}_{m,i} = \frac{x_{m,i} - \min_j x_{m,j}}{\max_j x_{m,j} - \min_j x_{m,j}}

    over the rows in ``mask`` (the reachable grasps), so that a weight is the
    share of the score a metric can move, whatever its units (Yoshikawa's
    index, clearance [m], joint-limit margin). A metric constant over the
    rows contributes its full weight to every row. ``normalization="rank"``
    uses ranks instead (``(rank - 1) / (n - 1)``, ties averaged): robust to
    outliers. Every metric is "higher is better". Metrics of weight 0 are
    ignored (their column may be missing).

    Args:
        columns: Metric name -> (N,) values (e.g. ``{"yoshikawa": t["manipulability"],
            "clearance": t["clearance"], "joint_limit_margin": ...}``).
        weights: Metric name -> weight >= 0, at least one > 0 (None:
            :data:`DEFAULT_COMBINED_WEIGHTS`).
        mask: (N,) bool rows to score (default: rows where every used metric is finite).
        normalization: ``"minmax"`` or ``"rank"``.

    Returns:
        (N,) scores in [0, 1]; NaN outside ``mask`` or where a used metric is NaN.

    Raises:
        ConfigError: Negative or non-finite weight, all weights zero, or a
            weighted metric without a column (names it and the columns given).
        InputError: Columns of different lengths.
    """
    w = dict(DEFAULT_COMBINED_WEIGHTS if weights is None else weights)
    if normalization not in ("minmax", "rank"):
        raise ConfigError(unknown_choice("normalization", normalization, ("minmax", "rank")))
    for name, value in w.items():
        if not np.isfinite(value) or value < 0:
            raise ConfigError(f"ranking.weights.{name} must be a number >= 0, got {value!r}")
    used = {k: float(v) for k, v in w.items() if v > 0}
    if not used:
        raise ConfigError(
            f"ranking.weights must have at least one positive weight, got {dict(w)!r}"
        )
    for name in used:
        if name not in columns:
            raise ConfigError(
                f"ranking.weights.{name}: no such metric column; "
                f"available: {', '.join(sorted(columns)) or '(none)'}"
            )
    cols = {k: np.asarray(columns[k], dtype=float) for k in used}
    n = {len(c) for c in cols.values()}
    if len(n) != 1:
        raise InputError(
            f"metric columns differ in length: { {k: len(c) for k, c in cols.items()} }"
        )
    size = n.pop()
    finite = np.all([np.isfinite(c) for c in cols.values()], axis=0)
    sel = finite if mask is None else (np.asarray(mask, dtype=bool) & finite)
    total = sum(used.values())
    score = np.zeros(size)
    for name, weight in used.items():
        x = cols[name][sel]
        if x.size == 0:
            continue
        if normalization == "rank":
            from scipy.stats import rankdata

            norm = (rankdata(x) - 1.0) / (x.size - 1) if x.size > 1 else np.ones_like(x)
        else:
            lo, hi = float(np.min(x)), float(np.max(x))
            norm = (x - lo) / (hi - lo) if hi > lo else np.ones_like(x)
        score[sel] += weight / total * norm
    score[~sel] = np.nan
    return score
