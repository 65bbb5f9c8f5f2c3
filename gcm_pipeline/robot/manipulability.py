r"""Dexterity metrics of the grasp frame, batched over N configurations.

All functions take Jacobians (N, 6, nq) of the grasp frame in
``LOCAL_WORLD_ALIGNED`` (rows ``[v; omega]``, as returned by
:meth:`~gcm_pipeline.robot.model.Robot.jacobian`) or configurations, and
return (N,) arrays:

* Yoshikawa's index :math:`w = \sqrt{\det(J J^\top)}` of the 6-D Jacobian,
  zero at a singular configuration (e.g. the stretched arm);
* its translational variant, with the three linear-velocity rows only
  (units [m^3]);
* the inverse condition number :math:`\sigma_{\min} / \sigma_{\max}` in [0, 1];
* the joint-limit margin :math:`\min_i \min(q_i - l_i, u_i - q_i) / ((u_i - l_i)/2)`
  in [0, 1]: 1 with every joint mid-range, 0 at a limit.

The 6-D index mixes [m] and [rad] rows, as Yoshikawa's original does; compare
its values for one robot only.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np

from gcm_pipeline.errors import InputError, choice_error

__all__ = [
    "METRICS",
    "inverse_condition_number",
    "joint_limit_margin",
    "manipulability",
    "manipulability_metrics",
    "translational_manipulability",
    "yoshikawa",
]


def _jac(jacobian: Any, rows: int = 6) -> np.ndarray:
    j = np.asarray(jacobian, dtype=float)
    if j.ndim == 2:
        j = j[None]
    if j.ndim != 3 or j.shape[1] != rows:
        raise InputError(f"jacobian must have shape (N, {rows}, nq), got {np.shape(jacobian)}")
    return j


_CHUNK = 8192


def _gram_det_sqrt(j: np.ndarray) -> np.ndarray:
    out = np.empty(j.shape[0])
    for a in range(0, j.shape[0], _CHUNK):
        jj = j[a : a + _CHUNK]
        out[a : a + _CHUNK] = np.linalg.det(jj @ jj.transpose(0, 2, 1))
    return np.sqrt(np.clip(out, 0.0, None))


def yoshikawa(jacobian: Any) -> np.ndarray:
    r"""Yoshikawa manipulability :math:`\sqrt{\det(J J^\top)}` of 6-D Jacobians.

    Args:
        jacobian: Grasp-frame Jacobians (N, 6, nq).

    Returns:
        (N,) values >= 0; 0 at singular configurations.
    """
    return _gram_det_sqrt(_jac(jacobian))


def translational_manipulability(jacobian: Any) -> np.ndarray:
    r"""Yoshikawa index of the translational rows, :math:`\sqrt{\det(J_v J_v^\top)}`.

    Args:
        jacobian: Grasp-frame Jacobians (N, 6, nq) or their linear rows (N, 3, nq).

    Returns:
        (N,) values >= 0 [m^3].
    """
    j = np.asarray(jacobian, dtype=float)
    if j.ndim == 3 and j.shape[1] == 3:
        return _gram_det_sqrt(j)
    return _gram_det_sqrt(_jac(j)[:, :3])


def inverse_condition_number(jacobian: Any) -> np.ndarray:
    r"""Inverse condition number :math:`\sigma_{\min}/\sigma_{\max}` of 6-D Jacobians.

    Args:
        jacobian: Grasp-frame Jacobians (N, 6, nq).

    Returns:
        (N,) values in [0, 1]; 0 at singular configurations.
    """
    j = _jac(jacobian)
    eig = np.empty((j.shape[0], 6))
    for a in range(0, j.shape[0], _CHUNK):
        jj = j[a : a + _CHUNK]
        eig[a : a + _CHUNK] = np.linalg.eigvalsh(jj @ jj.transpose(0, 2, 1))  # sigma^2, ascending
    eig = np.clip(eig, 0.0, None)
    top = eig[:, -1]
    out = np.zeros(j.shape[0])
    ok = top > 0
    out[ok] = np.sqrt(eig[ok, 0] / top[ok])
    return out


def joint_limit_margin(q: Any, lower: Any, upper: Any) -> np.ndarray:
    r"""Normalised distance to the nearest joint limit.

    .. math::

        m(q) = \min_i \frac{\min(q_i - l_i,\; u_i - q_i)}{(u_i - l_i)/2}

    Args:
        q: Configurations (N, nq) [rad].
        lower: Lower limits (nq,) [rad].
        upper: Upper limits (nq,) [rad].

    Returns:
        (N,) values: 1 with every joint mid-range, 0 at a limit, < 0 outside.
    """
    qs = np.asarray(q, dtype=float)
    if qs.ndim == 1:
        qs = qs[None]
    lo = np.asarray(lower, dtype=float)
    hi = np.asarray(upper, dtype=float)
    if qs.ndim != 2 or qs.shape[1] != lo.shape[0] or lo.shape != hi.shape:
        raise InputError(f"q must have shape (N, {lo.shape[0]}), got {np.shape(q)}")
    half = 0.5 * (hi - lo)
    return np.min(np.minimum(qs - lo, hi - qs) / half, axis=1)


METRICS: dict[str, str] = {
    "yoshikawa": "manipulability",
    "translational": "manip_translation",
    "inverse_condition": "inverse_condition",
    "joint_limit_margin": "joint_limit_margin",
}
"""Metric name (as used in configs) -> grasp-table column name."""


def manipulability_metrics(robot: Any, q: Any) -> dict[str, np.ndarray]:
    """Every metric of configurations, with one Jacobian evaluation.

    Rows of ``q`` with NaN give NaN metrics.

    Args:
        robot: A :class:`~gcm_pipeline.robot.model.Robot`.
        q: Configurations (N, nq) [rad].

    Returns:
        Metric name (see :data:`METRICS`) -> (N,) values.
    """
    qs = robot.as_configurations(q)
    ok = np.all(np.isfinite(qs), axis=1)
    out = {name: np.full(qs.shape[0], np.nan) for name in METRICS}
    if not np.any(ok):
        return out
    sub = qs if ok.all() else qs[ok]
    jac = robot.jacobian(sub)
    fns: dict[str, Callable[[], np.ndarray]] = {
        "yoshikawa": lambda: yoshikawa(jac),
        "translational": lambda: translational_manipulability(jac),
        "inverse_condition": lambda: inverse_condition_number(jac),
        "joint_limit_margin": lambda: joint_limit_margin(sub, robot.lower, robot.upper),
    }
    for name, fn in fns.items():
        out[name][ok] = fn()
    return out


def manipulability(robot: Any, q: Any, metric: str = "yoshikawa") -> np.ndarray:
    """One metric of configurations (N, nq) -> (N,).

    Args:
        robot: A :class:`~gcm_pipeline.robot.model.Robot`.
        q: Configurations (N, nq) [rad].
        metric: One of :data:`METRICS`.

    Raises:
        InputError: Unknown metric (lists the valid ones).
    """
    if metric not in METRICS:
        raise choice_error(InputError, "manipulability metric", metric, METRICS)
    qs = np.asarray(q, dtype=float)
    if metric == "joint_limit_margin":
        return joint_limit_margin(qs, robot.lower, robot.upper)
    jac = robot.jacobian(qs)
    if metric == "yoshikawa":
        return yoshikawa(jac)
    if metric == "translational":
        return translational_manipulability(jac)
    return inverse_condition_number(jac)
