"""The collision world of a run and the ``combined`` ranking metric.

* :func:`world_shapes` and :func:`make_checker` map the config sections
  ``environment``, ``object`` and ``robot.base_pose`` onto world shapes in the
  robot's base frame and a
  :class:`~gcm_pipeline.robot.collision.CollisionChecker` (the reachability
  engine, :mod:`gcm_pipeline.reach.engine`, uses it for the grasp, the
  approach and the retreat);
* :func:`combined_score` is the ``combined`` ranking metric.
"""

from __future__ import annotations

import logging
from collections.abc import Mapping
from typing import Any

import coal
import numpy as np

from gcm_pipeline.config import EnvironmentConfig, ObjectConfig, Pose
from gcm_pipeline.errors import ConfigError, InputError, unknown_choice
from gcm_pipeline.robot.collision import (
    REASON_ENVIRONMENT,
    REASON_OBJECT,
    REASON_SELF,
    CollisionChecker,
    WorldShape,
    as_transform,
    shape_geometry,
)
from gcm_pipeline.robot.model import Robot

log = logging.getLogger(__name__)

__all__ = [
    "COLLISION_REASONS",
    "DEFAULT_COMBINED_WEIGHTS",
    "combined_score",
    "make_checker",
    "world_shapes",
]

_ENV_SHAPES = ("box", "cylinder", "sphere", "mesh")

COLLISION_REASONS = (REASON_SELF, REASON_ENVIRONMENT, REASON_OBJECT)

#: Weights of the ``combined`` metric when the config gives none.
DEFAULT_COMBINED_WEIGHTS: dict[str, float] = {
    "yoshikawa": 1.0,
    "clearance": 0.5,
    "joint_limit_margin": 0.2,
}


def world_shapes(
    environment: EnvironmentConfig | None = None,
    object_cfg: ObjectConfig | None = None,
    base_pose: Pose | np.ndarray | None = None,
) -> list[WorldShape]:
    """The collision world of a config in the robot's base frame.

    * the support table (``environment.table``): a box whose top face is at
      ``table.height``, centred at ``center_xy``; the robot's base stands on it;
    * the ``environment.obstacles`` (box, cylinder, sphere, mesh; placed like
      the object: a cylinder stands on its base along its frame's z, boxes and
      spheres are centred on their frame);
    * the ``object`` (kind ``object``) unless ``environment.check_object`` is off.

    Args:
        environment: Config section (None: the default, a table at z = 0).
        object_cfg: Config ``object`` section or None.
        base_pose: Robot base in the world (Pose or (4, 4)); None: identity.

    Returns:
        The :class:`~gcm_pipeline.robot.collision.WorldShape` list.

    Raises:
        ConfigError: Unknown shape, missing or non-positive size.
        InputError: A mesh file is missing or unreadable (the message names it).
    """
    env = EnvironmentConfig() if environment is None else environment
    base_inv = np.linalg.inv(as_transform(base_pose))
    world: list[WorldShape] = []
    if env.table is not None:
        t = env.table
        for s in t.size:
            if not np.isfinite(s) or s <= 0:
                raise ConfigError(
                    f"environment.table: size must be positive numbers [m], got {s!r}"
                )
        sx, sy, sz = (float(s) for s in t.size)
        m = np.eye(4)
        m[:3, 3] = (t.center_xy[0], t.center_xy[1], t.height - 0.5 * sz)
        world.append(
            WorldShape("table", coal.Box(sx, sy, sz), base_inv @ m, "environment", support=True)
        )
    for i, obs in enumerate(env.obstacles):
        where = f"environment.obstacles[{i}]"
        if obs.shape not in _ENV_SHAPES:
            raise ConfigError(f"{where}: " + unknown_choice("shape", obs.shape, _ENV_SHAPES))
        made = shape_geometry(obs.shape, obs.dims, mesh=obs.mesh, scale=obs.scale, where=where)
        assert made is not None
        geom, centre = made
        world.append(
            WorldShape(
                obs.name or f"obstacle_{i}",
                geom,
                base_inv @ obs.pose.matrix() @ centre,
                "environment",
            )
        )
    if object_cfg is not None and env.check_object:
        made = shape_geometry(
            object_cfg.shape,
            object_cfg.dims,
            mesh=object_cfg.mesh,
            scale=object_cfg.scale,
            where="object",
        )
        assert made is not None
        world.append(
            WorldShape("object", made[0], base_inv @ object_cfg.pose.matrix() @ made[1], "object")
        )
    return world


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
    env = EnvironmentConfig() if environment is None else environment
    checker = CollisionChecker(
        robot,
        world_shapes(env, object_cfg, base_pose),
        contact_tolerance=env.contact_tolerance,
        self_collision=env.self_collision,
        threads=threads,
    )
    for link, shape in checker.static_collisions:
        log.warning(
            "%s overlaps the robot's fixed %s: every configuration collides "
            "(move it, or the robot: robot.base_pose)",
            shape,
            link,
        )
    return checker


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
