"""The ``robot`` and ``reachability`` steps: a config onto the robot, collision world and engine."""

from __future__ import annotations

import logging
from dataclasses import replace
from typing import Any

import numpy as np

from gcm_pipeline.config import robot_spec
from gcm_pipeline.config.reach_sections import ApproachConfig, EnvironmentConfig, RetreatConfig
from gcm_pipeline.config.run import Config, takes_config
from gcm_pipeline.config.sections import ObjectConfig, Pose
from gcm_pipeline.pipeline.clouds import (
    cloud_key,
    cloud_world,
    segment_groups,
    table_merge,
    table_subset,
)
from gcm_pipeline.reach import check as reach_check
from gcm_pipeline.reach.engine import ReachabilityEngine
from gcm_pipeline.reach.moves import Move
from gcm_pipeline.reach.options import ReachOptions
from gcm_pipeline.robot import collision
from gcm_pipeline.robot.collision import CollisionChecker, WorldShape
from gcm_pipeline.robot.model import Robot
from gcm_pipeline.table import GraspTable

log = logging.getLogger(__name__)


@takes_config
def robot_from_config(cfg: Config) -> Robot:
    """The robot of ``cfg.robot.spec`` (a shipped name or a spec YAML path) with ``robot.tool``."""
    return robot_spec.load_robot(cfg.robot.spec, cfg.robot.tool)


#: The same as :func:`robot_from_config` (``gcm_pipeline.load_robot`` is the
#: one of :mod:`gcm_pipeline.config.robot_spec`, by name or path).
load_robot = robot_from_config


def collision_world(
    environment: EnvironmentConfig | None = None,
    object_cfg: ObjectConfig | None = None,
    base_pose: Pose | np.ndarray | None = None,
    camera_pose: Pose | None = None,
    grasp_segment: int | None = None,
) -> list[WorldShape]:
    """The collision world of the config sections, in the robot's base frame.

    * the support table (``environment.table``): a box whose top face is at
      ``table.height``, centred at ``center_xy``; the robot's base stands on it;
    * the ``environment.obstacles`` (box, cylinder, sphere, mesh; placed like
      the object: a cylinder stands on its base along its frame's z, boxes and
      spheres are centred on their frame);
    * the ``environment.point_clouds``, as octree tiles
      (:func:`~gcm_pipeline.pipeline.clouds.cloud_world`; ``camera_pose`` is
      ``candidates.camera_pose``, for camera-frame clouds without their own);
    * the ``object`` (kind ``object``) unless ``environment.check_object`` is off.

    Args:
        environment: Config section (None: the default, a table at z = 0).
        object_cfg: Config ``object`` section or None.
        base_pose: Robot base in the world (Pose or (4, 4)); None: identity.
        camera_pose: ``candidates.camera_pose``: the pose of camera-frame clouds
            that give none.
        grasp_segment: The segment of the grasps checked (left out of the clouds).

    Returns:
        The :class:`~gcm_pipeline.robot.collision.WorldShape` list.

    Raises:
        ConfigError: Unknown shape, missing or non-positive size.
        InputError: A mesh file is missing or unreadable (the message names it).
    """
    env = EnvironmentConfig() if environment is None else environment
    base_inv = np.linalg.inv(collision.as_transform(base_pose))
    world: list[WorldShape] = []
    if env.table is not None:
        t = env.table
        world.append(collision.table_shape(t.size, t.center_xy, t.height, base_inv))
    for i, obs in enumerate(env.obstacles):
        world.append(
            collision.obstacle_shape(
                obs.name or f"obstacle_{i}",
                obs.shape,
                obs.dims,
                obs.pose.matrix(),
                base_inv,
                mesh=obs.mesh,
                scale=obs.scale,
                where=f"environment.obstacles[{i}]",
            )
        )
    world += cloud_world(env, object_cfg, base_inv, camera_pose, grasp_segment)
    if object_cfg is not None and env.check_object:
        o = object_cfg
        world.append(
            collision.object_shape(
                o.shape, o.dims, o.pose.matrix(), base_inv, mesh=o.mesh, scale=o.scale
            )
        )
    return world


def make_checker(
    robot: Robot,
    environment: EnvironmentConfig | None = None,
    object_cfg: ObjectConfig | None = None,
    base_pose: Pose | np.ndarray | None = None,
    *,
    threads: int = 1,
    camera_pose: Pose | None = None,
    grasp_segment: int | None = None,
) -> CollisionChecker:
    """The collision checker of a run (``environment``, ``object``, ``robot.base_pose``).

    Args:
        robot: The robot.
        environment: Config section (None: the default, a table at z = 0).
        object_cfg: Config ``object`` section or None.
        base_pose: Robot base in the world (Pose or (4, 4)); None: identity.
        threads: Threads for the batched checks.
        camera_pose: ``candidates.camera_pose`` (see :func:`collision_world`).
        grasp_segment: See :func:`collision_world`.

    Returns:
        The :class:`~gcm_pipeline.robot.collision.CollisionChecker`; a world
        shape overlapping the robot's fixed links is logged as a warning.
    """
    env = EnvironmentConfig() if environment is None else environment
    checker = CollisionChecker(
        robot,
        collision_world(env, object_cfg, base_pose, camera_pose, grasp_segment),
        contact_tolerance=env.contact_tolerance,
        self_collision=env.self_collision,
        threads=threads,
    )
    told = set()
    for link, shape in checker.static_collisions:
        cloud = cloud_key(env, shape)  # a cloud's tiles: one warning per cloud
        if (cloud or shape, link) in told:
            continue
        told.add((cloud or shape, link))
        log.warning(
            "%s overlaps the robot's fixed %s: every configuration collides "
            "(%s, or the robot: robot.base_pose)",
            cloud or shape,
            link,
            "move it" if cloud is None else "crop it: crop_min/crop_max or max_depth; or move it",
        )
    return checker


def approach_move(approach: ApproachConfig | None) -> Move | None:
    """The ``approach`` section as a :class:`Move` (backwards along the grasp frame's z)."""
    if approach is None:
        return None
    return Move(
        distance=approach.distance,
        direction=(0.0, 0.0, -1.0),
        frame="grasp",
        steps=approach.steps,
        max_joint_step=approach.max_joint_step,
        max_deviation=approach.max_deviation,
        holding=False,
    )


def retreat_move(retreat: RetreatConfig | None, base_pose: np.ndarray | None = None) -> Move | None:
    """The ``retreat`` section as a :class:`Move`; a world direction turned into the base frame."""
    if retreat is None:
        return None
    direction = np.asarray(retreat.direction, dtype=float)
    frame = "grasp"
    if retreat.frame == "world":
        frame = "base"
        if base_pose is not None:
            direction = np.asarray(base_pose[:3, :3], dtype=float).T @ direction
    return Move(
        distance=retreat.distance,
        direction=tuple(direction.tolist()),
        frame=frame,
        steps=retreat.steps,
        max_joint_step=retreat.max_joint_step,
        max_deviation=retreat.max_deviation,
        holding=True,
    )


@takes_config
def reach_options(cfg: Config) -> ReachOptions:
    """The reachability options of a config.

    Reads ``ik``, ``robot.base_pose``, ``approach``, ``retreat`` and ``seed``.
    """
    ik = cfg.ik
    base_pose = cfg.robot.base_pose.matrix()
    return ReachOptions(
        backend=ik.backend,
        position_tolerance=ik.position_tolerance,
        orientation_tolerance=ik.orientation_tolerance,
        approach=approach_move(cfg.approach),
        retreat=retreat_move(cfg.retreat, base_pose),
        workers=ik.workers,
        solutions=ik.solutions,
        seed=cfg.seed,
        base_pose=base_pose,
    )


@takes_config
def reachability_engine(
    robot: Robot, cfg: Config, *, grasp_segment: int | None = None
) -> ReachabilityEngine:
    """The reachability engine of a config.

    Reads ``ik``, ``environment``, ``object``, ``approach``, ``retreat``,
    ``robot.base_pose`` and ``seed`` (:func:`reach_options`; the
    ``environment`` and ``object`` sections become the collision checker).
    Build it once to check many pose sets with the same robot, seed library and
    collision world (:func:`check_reachability` with ``engine=``); close it (or
    use a ``with`` block) to stop its worker processes. ``grasp_segment``: the
    segment of the grasps it checks, left out of the point clouds.
    """
    options = reach_options(cfg)
    checker = None
    if cfg.environment is not None or cfg.object is not None:
        checker = make_checker(
            robot,
            cfg.environment,
            cfg.object,
            options.base_pose,
            camera_pose=cfg.candidates.camera_pose,
            grasp_segment=grasp_segment,
        )
    return reach_check.make_engine(robot, options, checker=checker)


@takes_config
def check_reachability(
    grasps: GraspTable,
    robot: Robot,
    cfg: Config,
    *,
    progress: bool = False,
    engine: ReachabilityEngine | None = None,
) -> GraspTable:
    """IK, collision, approach and retreat checks for every grasp (``ik`` and friends).

    "Reachable" means an IK solution within the ``ik`` tolerances whose
    configuration is collision-free (``environment`` and ``object``), with an
    ``approach`` section whose straight-line pre-grasp approach is followable
    and collision-free, and with a ``retreat`` section whose post-grasp
    retreat (holding the object) is too; see
    :class:`gcm_pipeline.reach.engine.ReachabilityEngine` for the sequence and
    :func:`reach_options` for the mapping.

    Args:
        grasps: Table with ``dq`` (world poses of the grasp frame).
        robot: From :func:`robot_from_config`.
        cfg: The full config.
        progress: Show per-target progress (a bar on a terminal, else a log
            line every few seconds).
        engine: The engine of :func:`reachability_engine` for this config, to
            reuse one across calls (default: built for this call and closed;
            with point clouds that leave out each grasp's own segment, one per
            segment, :func:`~gcm_pipeline.pipeline.clouds.segment_groups`).

    Returns:
        The table with ``reachable, reason, q, pos_err, rot_err``,
        ``q_pregrasp, q_retreat, q_rejected`` (and ``clearance``) added.
    """
    groups = segment_groups(grasps, cfg.environment) if engine is None else None
    if groups is not None:  # each grasp without its own segment of the clouds
        parts = []
        for segment, rows in groups:
            with reachability_engine(robot, cfg, grasp_segment=segment) as eng:
                part = check_reachability(
                    table_subset(grasps, rows), robot, cfg, progress=progress, engine=eng
                )
            parts.append((rows, part))
        return table_merge(grasps, parts)
    own = engine is None
    eng = reachability_engine(robot, cfg) if engine is None else engine
    try:
        done = reach_check.check_reachability(
            grasps, robot, reach_options(cfg), engine=eng, progress=progress
        )
    finally:
        if own:
            eng.close()
    assert isinstance(done, GraspTable)  # no return_candidates
    return done


class ReachabilityCheck:
    """Checks any grasp poses the way the run's reachability stage does.

    The same IK backend, tolerances, collision world, approach and retreat as
    :func:`check_reachability` with ``cfg``; the engine (robot, seed library,
    collision world) is built once and reused, so the adaptive refinement, IK
    re-seeding and manifold queries can call it many times on small batches.
    Each call may pass warm starts: configurations tried first, before the
    backend's usual seeds.

    Args:
        robot: The robot.
        cfg: The full config.

    Attributes:
        solved: Number of poses checked so far (IK targets).
    """

    def __init__(self, robot: Robot, cfg: Config) -> None:
        self.robot = robot
        self.config = cfg
        self.solved = 0
        self.engine = reachability_engine(robot, cfg)
        segmented = cfg.candidates.format == "contact_graspnet"  # grasps with a segment
        if segmented and any(pc.exclude_grasp_segment for pc in cfg.environment.point_clouds):
            log.warning(
                "densify.adaptive and continuity.reseed check poses against the whole "
                "point clouds: each grasp's own segment is left out in the reachability "
                "stage only; list the target's segment in exclude_segments"
            )

    def __call__(self, dq: np.ndarray, seeds: np.ndarray | None = None) -> GraspTable:
        """Check poses (M, 8) (world) with optional warm starts (M, K, nq) [rad].

        Returns:
            A table of M rows: ``dq, reachable, reason, q, pos_err, rot_err``
            (and ``clearance`` with collisions), as the reachability stage.
        """
        cfg = self.config
        dq = np.asarray(dq, dtype=np.float64).reshape(-1, 8)
        table = GraspTable({"dq": dq})
        if not len(dq):
            return _empty_reachability(
                table, self.robot.nq, with_clearance=self.engine.checker is not None
            )
        done = reach_check.check_reachability(
            table,
            self.robot,
            replace(reach_options(cfg), warm_start=False),
            seeds=None if seeds is None else np.asarray(seeds, dtype=np.float64),
            engine=self.engine,
        )
        assert isinstance(done, GraspTable)
        self.solved += len(dq)
        return done

    def close(self) -> None:
        """Stop the engine's worker processes, if any ran."""
        self.engine.close()

    def __repr__(self) -> str:
        return f"ReachabilityCheck(robot={self.robot.name!r}, solved={self.solved})"


def _empty_reachability(table: GraspTable, nq: int, *, with_clearance: bool) -> GraspTable:
    """The reachability columns of a table with no rows."""
    cols: dict[str, Any] = dict(
        reachable=np.zeros(0, dtype=bool),
        reason=np.zeros(0, dtype="<U1"),
        q=np.zeros((0, nq)),
        pos_err=np.zeros(0),
        rot_err=np.zeros(0),
        q_pregrasp=np.zeros((0, nq)),
        q_retreat=np.zeros((0, nq)),
        q_rejected=np.zeros((0, nq)),
    )
    if with_clearance:
        cols["clearance"] = np.zeros(0)
    return GraspTable({"dq": np.zeros((0, 8)), **cols})
