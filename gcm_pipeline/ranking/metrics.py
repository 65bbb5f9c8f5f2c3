r"""The ranking metrics: their names, their columns and the ``combined`` metric.

Four metrics come from the arm's kinematics (:mod:`gcm_pipeline.robot.manipulability`),
two from other steps (``clearance`` from the collision checks, ``margin`` from
the manifold), one from the source (``score``: the synthesiser's grasp quality),
and ``combined`` weighs them:

.. math::

    s_i = \sum_m \frac{w_m}{\sum_k w_k} \, \frac{x_{m,i} - lo_m}{hi_m - lo_m}

with :math:`[lo_m, hi_m]` the range of metric :math:`m` over the rows it is
normalised on (a metric constant there adds its full weight to every row).
:func:`weighted_sum` is that sum, the one definition every user of the
``combined`` metric calls: the ranking (:func:`combined_score` over the
reachable rows), the choice of an IK branch (over every branch) and the
queries of a finished run (over the run's rows).
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np

from gcm_pipeline.errors import ConfigError, InputError, choice_error
from gcm_pipeline.robot.manipulability import METRICS

__all__ = [
    "DEFAULT_COMBINED_WEIGHTS",
    "METRICS",
    "METRIC_COLUMNS",
    "combined_score",
    "value_range",
    "weighted_sum",
]

#: Ranking metric (config name) -> the grasp-table column holding it.
METRIC_COLUMNS: dict[str, str] = {
    **METRICS,
    "clearance": "clearance",
    "margin": "margin",
    "score": "score",
    "combined": "combined",
}

#: Weights of the ``combined`` metric when the config gives none.
DEFAULT_COMBINED_WEIGHTS: dict[str, float] = {
    "yoshikawa": 1.0,
    "clearance": 0.5,
    "joint_limit_margin": 0.2,
}


def value_range(x: np.ndarray) -> tuple[float, float]:
    """``(min, max)`` of the finite values of ``x``; ``(0, 1)`` when none is finite."""
    ok = np.isfinite(x)
    return (float(x[ok].min()), float(x[ok].max())) if ok.any() else (0.0, 1.0)


def weighted_sum(
    values: Mapping[str, np.ndarray],
    weights: Mapping[str, float],
    ranges: Mapping[str, tuple[float, float]],
    shape: int | tuple[int, ...],
) -> np.ndarray:
    """The ``combined`` metric: the weighted sum of metrics normalised by their ranges.

    Args:
        values: Metric name -> values of ``shape``.
        weights: Metric name -> weight > 0 (the metrics summed, in this order).
        ranges: Metric name -> ``(lo, hi)`` it is normalised by; ``hi <= lo``:
            the metric adds its full weight everywhere.
        shape: Shape of the result (and of every value array).

    Returns:
        Scores of ``shape``; NaN where a summed metric is NaN.
    """
    total = sum(weights.values())
    score = np.zeros(shape)
    for name, w in weights.items():
        lo, hi = ranges[name]
        x = values[name]
        score += w / total * ((x - lo) / (hi - lo) if hi > lo else np.ones_like(x))
    return score


def combined_score(
    columns: Mapping[str, Any],
    weights: Mapping[str, float] | None = None,
    *,
    mask: Any = None,
    normalization: str = "minmax",
) -> np.ndarray:
    r"""Weighted combination of ranking metrics, each normalised to [0, 1] over ``mask``.

    :func:`weighted_sum` over the rows in ``mask`` (the reachable grasps), each
    metric normalised by its range there, so that a weight is the share of the
    score a metric can move, whatever its units (Yoshikawa's index, clearance
    [m], joint-limit margin). ``normalization="rank"`` uses ranks instead
    (``(rank - 1) / (n - 1)``, ties averaged): robust to outliers. Every metric
    is "higher is better". Metrics of weight 0 are ignored (their column may
    be missing).

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
        raise choice_error(ConfigError, "normalization", normalization, ("minmax", "rank"))
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
    picked = {name: c[sel] for name, c in cols.items()}
    if normalization == "rank":
        # scipy.stats costs 0.35 s to import, paid by every run if at the top; only
        # rank normalisation needs it
        from scipy.stats import rankdata

        m = int(sel.sum())
        picked = {
            name: (rankdata(x) - 1.0) / (m - 1) if m > 1 else np.ones_like(x)
            for name, x in picked.items()
        }
        ranges = dict.fromkeys(picked, (0.0, 1.0))
    else:
        ranges = {name: value_range(x) for name, x in picked.items()}
    score = np.full(size, np.nan)
    score[sel] = weighted_sum(picked, used, ranges, int(sel.sum()))
    return score
