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

Three more metrics rank by columns of other stages (the collision checks,
:mod:`gcm_pipeline.robot.collision`; the margin,
:mod:`gcm_pipeline.manifold.margin`):

================================ ======================= ====================
``clearance``                    ``clearance``           distance of the arm to
                                                         environment and object [m]
``margin``                       ``margin``              distance along the manifold
                                                         to the nearest unreachable
                                                         point [m] (``inf``: none)
``combined``                     ``combined`` (added)    weighted sum of normalised
                                                         metrics, see
                                                         :func:`combined_score`
================================ ======================= ====================

plus ``rank`` (N,) int: 1-based among the reachable grasps, by the chosen
metric in decreasing order, ties broken by row index (lower first); 0 for
unreachable grasps. ``top`` (N,) bool marks ranks 1..``top_k``.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np

from gcm_pipeline.errors import ConfigError, InputError, unknown_choice
from gcm_pipeline.robot.manipulability import METRICS, manipulability_metrics
from gcm_pipeline.robot.model import Robot, RobotSpec, as_robot
from gcm_pipeline.table import GraspTable

__all__ = ["DEFAULT_COMBINED_WEIGHTS", "METRICS", "METRIC_COLUMNS", "combined_score", "rank"]

#: Ranking metric (config name) -> the grasp-table column holding it.
METRIC_COLUMNS: dict[str, str] = {
    **METRICS,
    "clearance": "clearance",
    "margin": "margin",
    "combined": "combined",
}

#: Weights of the ``combined`` metric when the config gives none.
DEFAULT_COMBINED_WEIGHTS: dict[str, float] = {
    "yoshikawa": 1.0,
    "clearance": 0.5,
    "joint_limit_margin": 0.2,
}


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
            ``clearance``, ``margin``, ``combined`` (``margin``: ``inf`` counts
            as the largest finite margin).
        top_k: How many of the best grasps ``top`` marks (None: all reachable).
        weights: Metric name -> weight of the ``combined`` metric (None:
            :data:`DEFAULT_COMBINED_WEIGHTS`);
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
            :func:`combined_score`).
    """
    if metric not in METRIC_COLUMNS:
        raise InputError(unknown_choice("ranking metric", metric, METRIC_COLUMNS))
    if top_k is not None and (
        isinstance(top_k, bool) or not isinstance(top_k, (int, np.integer)) or top_k < 0
    ):
        raise InputError(f"top_k must be an int >= 0 or None, got {top_k!r}")
    robot = as_robot(robot)
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
    for col in ("reachable", "q"):
        if col not in grasps:
            raise InputError(
                f"ranking needs column {col!r} (run reachability first); "
                f"columns: {', '.join(grasps.columns)}"
            )
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
        key = extra["combined"] = combined_score(scored, weights, mask=reachable)
    elif metric == "clearance":
        key = _finite_margin(grasps["clearance"], reachable)
    elif metric == "margin":
        key = _finite_margin(grasps["margin"], reachable)
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
