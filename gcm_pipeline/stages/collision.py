"""The collision world of a run.

* :func:`world_shapes` and :func:`make_checker` map the config sections
  ``environment``, ``object`` and ``robot.base_pose`` onto world shapes in the
  robot's base frame and a
  :class:`~gcm_pipeline.robot.collision.CollisionChecker` (the reachability
  engine, :mod:`gcm_pipeline.reach.engine`, uses it for the grasp, the
  approach and the retreat).
"""

from __future__ import annotations

import logging

import coal
import numpy as np

from gcm_pipeline.config import EnvironmentConfig, ObjectConfig, Pose
from gcm_pipeline.errors import ConfigError, unknown_choice
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
    "make_checker",
    "world_shapes",
]

_ENV_SHAPES = ("box", "cylinder", "sphere", "mesh")

COLLISION_REASONS = (REASON_SELF, REASON_ENVIRONMENT, REASON_OBJECT)


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
