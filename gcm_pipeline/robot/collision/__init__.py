"""Collision checking of robot configurations against itself, the world and the object.

* :mod:`~gcm_pipeline.robot.collision.world`: the world's shapes (table,
  obstacles, object) as coal geometries in the robot's base frame;
* :mod:`~gcm_pipeline.robot.collision.pairs`: which pairs are checked in which
  mode, and the reason a colliding configuration gets;
* :mod:`~gcm_pipeline.robot.collision.checker`: :class:`CollisionChecker`, its
  narrow phase and modes (``grasp``, ``approach``, ``retreat``);
* :mod:`~gcm_pipeline.robot.collision.broadphase` and
  :mod:`~gcm_pipeline.robot.collision.spheres`: the vectorised broad phase
  and the sphere covers it bounds geometries with;
* :mod:`~gcm_pipeline.robot.collision.clearance`: distances to the world;
* :mod:`~gcm_pipeline.robot.collision.contact`: the gripper's contact
  tolerance against a mesh object (eroded convex pieces, a solid mesh).

The package takes plain shapes and arrays and knows no config: the run's
config is mapped onto it in :mod:`gcm_pipeline.pipeline`.
"""

from gcm_pipeline.robot.collision.checker import CollisionChecker
from gcm_pipeline.robot.collision.pairs import (
    COLLISION_REASONS,
    MODES,
    REASON_ENVIRONMENT,
    REASON_OBJECT,
    REASON_SELF,
    gripper_links,
)
from gcm_pipeline.robot.collision.spheres import SphereCover, sphere_cover
from gcm_pipeline.robot.collision.world import (
    WorldShape,
    as_transform,
    depth_below,
    depth_into,
    lift_out_of,
    object_shape,
    obstacle_shape,
    table_shape,
)

__all__ = [
    "COLLISION_REASONS",
    "MODES",
    "REASON_ENVIRONMENT",
    "REASON_OBJECT",
    "REASON_SELF",
    "CollisionChecker",
    "SphereCover",
    "WorldShape",
    "as_transform",
    "depth_below",
    "depth_into",
    "lift_out_of",
    "gripper_links",
    "object_shape",
    "obstacle_shape",
    "sphere_cover",
    "table_shape",
]
