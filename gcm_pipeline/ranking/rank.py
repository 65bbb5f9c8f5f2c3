"""Ranking stage: manipulability metrics of the reachable grasps and their rank.

Reads ``reachable`` and ``q`` (from the reachability stage) and adds one
column per metric of :mod:`gcm_pipeline.robot.manipulability` (NaN for
unreachable rows):

================================ ======================= ====================
metric name (configs)            column                  meaning
================================ ======================= ====================
``yoshikawa``                    ``manipulability``      sqrt(det(J J^T)), 6-D
``translational``                ``manip_translation``   same, linear rows [m^3]
``inverse_condition``            ``inverse_condition``   sigma_min / sigma_max
``joint_limit_margin``           ``joint_limit_margin``  normalised, in [0, 1]
================================ ======================= ====================

Four more metrics rank by columns of other stages or of the source (the collision checks,
:mod:`gcm_pipeline.reach.engine`; the margin,
:mod:`gcm_pipeline.manifold.margin`):

================================ ======================= ====================
``clearance``                    ``clearance``           distance of the arm to
                                                         environment and object [m]
``margin``                       ``margin``              distance along the manifold
                                                         to the nearest unreachable
                                                         point [m] (``inf``: none)
``score``                        ``score``               the source's grasp quality
                                                         (a file's score, blended on
                                                         interpolated rows)
``combined``                     ``combined`` (added)    weighted sum of normalised
                                                         metrics, see
                                                         :func:`~gcm_pipeline.ranking.metrics.combined_score`
================================ ======================= ====================

plus ``rank`` (N,) int: 1-based among the reachable grasps, by the chosen
metric in decreasing order, ties broken by row index (lower first); 0 for
unreachable grasps. ``top`` (N,) bool marks ranks 1..``top_k``.
"""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np

from gcm_pipeline.errors import InputError, choice_error
from gcm_pipeline.ranking.metrics import (
    DEFAULT_COMBINED_WEIGHTS,
    METRIC_COLUMNS,
    METRICS,
    combined_score,
    value_range,
    weighted_sum,
)
from gcm_pipeline.robot.manipulability import manipulability_metrics
from gcm_pipeline.robot.model import Robot, RobotSpec, as_robot
from gcm_pipeline.table import GraspTable

__all__ = ["branch_scores", "rank", "reachable_score"]


def _finite_margin(values: np.ndarray, reachable: np.ndarray) -> np.ndarray:
    """Margins with ``inf`` (no unreachable point in reach) as the largest finite one.

    Ranks the unbounded grasps first (ties by row) and keeps min-max
    normalisation finite; all ``inf`` gives a constant column.
    """
    m = np.array(values, dtype=float)
    finite = np.isfinite(m) & reachable
    top = float(m[finite].max()) if finite.any() else 1.0
    m[np.isposinf(m)] = top
    return m


def _check_columns(grasps: GraspTable, metric: str, weights: Mapping[str, float] | None) -> None:
    """Refuse a table without a column the metric (or a ``combined`` weight) needs."""
    weight_of = (DEFAULT_COMBINED_WEIGHTS if weights is None else weights).get
    needs_clearance = metric == "clearance" or (
        metric == "combined" and weight_of("clearance", 0) > 0
    )
    if needs_clearance and "clearance" not in grasps:
        raise InputError(
            f"ranking metric {metric!r} needs the 'clearance' column of the collision "
            f"checks (reachability with an environment or object); "
            f"columns: {', '.join(grasps.columns)}"
        )
    needs_margin = metric == "margin" or (metric == "combined" and weight_of("margin", 0) > 0)
    if needs_margin and "margin" not in grasps:
        raise InputError(
            f"ranking metric {metric!r} needs the 'margin' column (the pipeline adds it "
            f"after reachability); columns: {', '.join(grasps.columns)}"
        )
    needs_score = metric == "score" or (metric == "combined" and weight_of("score", 0) > 0)
    if needs_score and "score" not in grasps:
        raise InputError(
            f"ranking metric {metric!r} needs the 'score' column (a grasp file's quality or "
            f"the antipodal sampler's); columns: {', '.join(grasps.columns)}"
        )
    for col in ("reachable", "q"):
        if col not in grasps:
            raise InputError(
                f"ranking needs column {col!r} (run reachability first); "
                f"columns: {', '.join(grasps.columns)}"
            )


def rank(
    grasps: GraspTable,
    robot: Robot | RobotSpec,
    *,
    metric: str = "yoshikawa",
    top_k: int | None = 10,
    weights: Mapping[str, float] | None = None,
) -> GraspTable:
    """Add the manipulability metrics, ``rank`` and ``top`` to the table.

    Args:
        grasps: Table with ``reachable`` (N,) and ``q`` (N, nq) (and
            ``clearance`` (N,) for the ``clearance`` and ``combined`` metrics).
        robot: A :class:`Robot` or a :class:`RobotSpec`.
        metric: Ranking metric, one of :data:`METRIC_COLUMNS`: ``yoshikawa``,
            ``translational``, ``inverse_condition``, ``joint_limit_margin``,
            ``clearance``, ``margin``, ``score``, ``combined`` (``margin``: ``inf``
            counts as the largest finite margin; ``score`` needs the ``score`` column).
        top_k: How many of the best grasps ``top`` marks (None: all reachable).
        weights: Metric name -> weight of the ``combined`` metric (None:
            :data:`~gcm_pipeline.ranking.metrics.DEFAULT_COMBINED_WEIGHTS`);
            ignored by the other metrics.

    Returns:
        The table with ``manipulability``, ``manip_translation``,
        ``inverse_condition``, ``joint_limit_margin``, ``rank`` and ``top``
        (and ``combined`` for that metric) added.

    Raises:
        InputError: Unknown metric (lists the valid ones), bad ``top_k``,
            missing columns (``clearance`` names the metric that needs it),
            or ``q`` of the wrong width.
        ConfigError: Bad ``weights`` (see
            :func:`~gcm_pipeline.ranking.metrics.combined_score`).
    """
    if metric not in METRIC_COLUMNS:
        raise choice_error(InputError, "ranking metric", metric, METRIC_COLUMNS)
    if top_k is not None and (
        isinstance(top_k, bool) or not isinstance(top_k, (int, np.integer)) or top_k < 0
    ):
        raise InputError(f"top_k must be an int >= 0 or None, got {top_k!r}")
    robot = as_robot(robot)
    _check_columns(grasps, metric, weights)
    n = len(grasps)
    reachable = np.asarray(grasps["reachable"], dtype=bool)
    q = np.asarray(grasps["q"], dtype=float)
    if q.shape != (n, robot.nq):
        raise InputError(f"grasp column 'q' must have shape ({n}, {robot.nq}), got {q.shape}")
    q_ok = np.where(reachable[:, None], q, np.nan)
    metrics = manipulability_metrics(robot, q_ok)
    columns = {METRICS[name]: values for name, values in metrics.items()}
    extra: dict[str, np.ndarray] = {}
    if metric == "combined":
        scored = dict(metrics)
        if "clearance" in grasps:  # inf: nothing to collide with (as a margin's inf)
            scored["clearance"] = _finite_margin(grasps["clearance"], reachable)
        if "margin" in grasps:
            scored["margin"] = _finite_margin(grasps["margin"], reachable)
        if "score" in grasps:
            scored["score"] = np.asarray(grasps["score"], dtype=float)
        key = extra["combined"] = combined_score(scored, weights, mask=reachable)
    elif metric == "clearance":
        key = _finite_margin(grasps["clearance"], reachable)
    elif metric == "margin":
        key = _finite_margin(grasps["margin"], reachable)
    elif metric == "score":
        key = np.asarray(grasps["score"], dtype=float)
    else:
        key = columns[METRICS[metric]]
    rows = np.flatnonzero(reachable & np.isfinite(key))
    # descending metric, then ascending row index
    order = rows[np.lexsort((rows, -key[rows]))]
    ranks = np.zeros(n, dtype=int)
    ranks[order] = np.arange(1, order.size + 1)
    k = order.size if top_k is None else int(top_k)
    top = (ranks > 0) & (ranks <= k)
    return grasps.with_columns(**columns, rank=ranks, top=top, **extra)


def reachable_score(
    table: GraspTable,
    robot: Robot,
    *,
    metric: str = "yoshikawa",
    weights: Mapping[str, float] | None = None,
) -> np.ndarray:
    """A ranking metric of the rows checked so far (``reachable``, ``q``); NaN: unreachable.

    ``combined`` is normalised over the reachable rows of ``table`` (its
    weights of metrics the table lacks are left out); ``margin`` (which needs
    the finished manifold) falls back to Yoshikawa's index, as does ``score``
    on a table without one.
    """
    reach = np.asarray(table["reachable"], dtype=bool)
    q = np.where(reach[:, None], np.asarray(table["q"], dtype=np.float64), np.nan)
    values: dict[str, np.ndarray] = dict(manipulability_metrics(robot, q))
    if "clearance" in table:
        values["clearance"] = np.asarray(table["clearance"], dtype=np.float64)
    if "score" in table:
        values["score"] = np.where(reach, np.asarray(table["score"], dtype=np.float64), np.nan)
    if metric == "combined":
        used = {k: v for k, v in (weights or {}).items() if k in values}
        return combined_score(values, used or None, mask=reach)
    return values.get(metric, values["yoshikawa"])


def branch_scores(
    solutions: np.ndarray,
    robot: Robot,
    *,
    metric: str = "yoshikawa",
    weights: Mapping[str, float] | None = None,
    clearance: np.ndarray | None = None,
) -> np.ndarray:
    """The ranking metric of every IK branch (N, K), higher is better.

    ``combined`` normalises each metric over all branches of all grasps (NaN
    branches aside); ``margin`` and ``score`` are the same for every branch of
    a grasp, so branches are compared by Yoshikawa's index instead (also their
    weights in ``combined`` are left out).

    Args:
        solutions: The branches (N, K, nq) [rad] (NaN past a grasp's last one).
        robot: The robot.
        metric: The ranking metric.
        weights: The ``combined`` metric's weights (None or empty:
            :data:`~gcm_pipeline.ranking.metrics.DEFAULT_COMBINED_WEIGHTS`).
        clearance: The branches' clearance (N, K) [m], if checked.
    """
    sol = np.asarray(solutions, dtype=np.float64)
    n, k, nq = sol.shape
    metrics = manipulability_metrics(robot, sol.reshape(-1, nq))
    values = {name: v.reshape(n, k) for name, v in metrics.items()}
    if clearance is not None:
        values["clearance"] = np.asarray(clearance, dtype=np.float64)
    if metric != "combined":
        return values.get(metric, values["yoshikawa"])
    used = {
        name: float(w)
        for name, w in (weights or DEFAULT_COMBINED_WEIGHTS).items()
        if w > 0 and name in values
    }
    ranges = {name: value_range(values[name]) for name in used}
    return weighted_sum(values, used, ranges, (n, k))
