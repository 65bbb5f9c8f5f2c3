"""The pipeline: candidates -> manifold -> densify -> reachability -> ranking -> publish.

Each stage is usable alone with the full :class:`~gcm_pipeline.config.Config`;
these functions map the config sections onto the keyword arguments of the
lower-level stage functions in :mod:`gcm_pipeline.stages`:

======================================== =====================================
function                                 reads / adds
======================================== =====================================
:func:`generate_candidates` ``(cfg)``    ``candidates``, ``object``, ``seed``
                                         -> table with ``dq``
:func:`build_manifold` ``(grasps, cfg)`` ``manifold`` (+ object pose as the
                                         chart frame) -> ``Manifold``
:func:`densify` ``(grasps, manifold,     ``densify`` -> table with ``origin``,
cfg)``                                   ``triangle``, ``vertices``, ``weights``
:func:`robot_from_config` ``(cfg)``      ``robot.spec`` -> ``Robot``
:func:`check_reachability` ``(grasps,    ``ik``, ``robot.base_pose``,
robot, cfg)``                            ``environment``, ``approach``, ``retreat``,
                                         ``object`` -> ``reachable, reason, q, ...``
:func:`rank` ``(grasps, robot, cfg)``    ``ranking`` -> ``manipulability``, ``rank``
:func:`publish` ``(result, cfg,          ``publish`` -> ``scene.html``, ``*.png``
out_dir)``
======================================== =====================================

``densify`` takes the candidate table as well as the manifold: the manifold
holds row ids into the candidate table, not poses, so that the poses live in
one place (the table's ``dq`` column) only.

:class:`Pipeline` runs them in order, times them, writes the run directory
atomically (:mod:`gcm_pipeline.rundir`) and returns a :class:`RunResult`. Before
any stage runs, the output directory is checked and :func:`preflight` (also
behind ``gcm validate``) checks what the config refers to: the robot spec,
every input file (named by its config key) and, with the live viewer on, the
meshcat server at ``publish.zmq_url``.
"""

from __future__ import annotations

import functools
import logging
import time
from collections.abc import Callable, Iterable, Iterator, Mapping
from contextlib import AbstractContextManager, contextmanager
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
from tqdm.auto import tqdm

from gcm_pipeline import sources
from gcm_pipeline.config.run import Config, load_config, takes_config
from gcm_pipeline.config.sections import CandidatesConfig
from gcm_pipeline.errors import ConfigError, InputError
from gcm_pipeline.geometry.dualquat import dq_from_matrix, dq_to_pos_quat
from gcm_pipeline.rundir import run as run_files
from gcm_pipeline.rundir import transaction
from gcm_pipeline.table import GraspTable

if TYPE_CHECKING:  # the stage modules import Pinocchio: loaded when a stage runs
    from gcm_pipeline.config.reach_sections import (
        ApproachConfig,
        EnvironmentConfig,
        RetreatConfig,
    )
    from gcm_pipeline.config.sections import ObjectConfig, Pose
    from gcm_pipeline.manifold.build import Manifold
    from gcm_pipeline.manifold.query import GraspManifold
    from gcm_pipeline.reach.engine import ReachabilityEngine
    from gcm_pipeline.reach.moves import Move
    from gcm_pipeline.reach.options import ReachOptions
    from gcm_pipeline.robot.collision import CollisionChecker, WorldShape
    from gcm_pipeline.robot.model import Robot

__all__ = [
    "STEPS",
    "ConfigRunQueries",
    "Pipeline",
    "ReachabilityCheck",
    "RunResult",
    "add_continuity",
    "approach_move",
    "branch_scores",
    "build_manifold",
    "candidate_poses",
    "check_reachability",
    "collision_world",
    "densify",
    "densify_adaptive",
    "generate_candidates",
    "grasp_manifold",
    "input_files",
    "load_manifold",
    "make_checker",
    "preflight",
    "publish",
    "rank",
    "reach_options",
    "reachability_engine",
    "retreat_move",
    "robot_from_config",
    "select_branches",
    "top_grasps",
    "unreachable_hint",
]

log = logging.getLogger(__name__)


def candidate_poses(
    cfg: Config, report: dict[str, Any] | None = None
) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    """World poses (N, 4, 4) of the grasp frame and per-candidate columns: ``candidates`` -> source.

    A file's poses go onto the grasp frame (:func:`~gcm_pipeline.sources.to_grasp_frame`)
    and into the world by ``candidates.camera_pose``, else by the object pose for
    ``frame: object``; generated and sampled grasps are mapped by ``grasp_to_tool``
    (on the right) and the object pose. ``report`` gets ``grasp_frame`` when a
    file's gripper frame was mapped.
    """
    c, obj = cfg.candidates, cfg.object
    to_tool = None if c.grasp_to_tool is None else c.grasp_to_tool.matrix()
    if c.source == "file":
        assert c.path is not None
        fmt = sources.file_format(c.path, c.format)
        grasps = sources.read_grasps(
            c.path, fmt, success_only=c.success_only, limit=c.limit, max_count=c.max_count
        )
        poses, choice = sources.to_grasp_frame(
            grasps, c.path, fmt, gripper=c.gripper, grasp_to_tool=to_tool
        )
        if choice is not None and report is not None:
            report["grasp_frame"] = choice.as_dict() | {"describe": choice.describe()}
        if c.camera_pose is not None:
            poses = c.camera_pose.matrix() @ poses
        elif c.frame == "object":
            if obj is None:
                raise ConfigError("candidates.frame 'object' needs an 'object' section")
            poses = obj.pose.matrix() @ poses
        return poses, grasps.columns
    rng = np.random.default_rng(c.seed if c.seed is not None else cfg.seed)
    if c.source == "antipodal":
        if obj is None:
            raise ConfigError("candidates.source 'antipodal' samples an object: add 'object'")
        gripper = sources.get_gripper(c.gripper or "franka_panda")
        d = obj.dims
        mesh = sources.object_mesh(
            obj.shape, radius=d.radius, height=d.height, size=d.size, mesh=obj.mesh, scale=obj.scale
        )
        table = cfg.environment.table
        poses, columns = sources.antipodal_candidates(
            mesh,
            c.count,
            gripper,
            rng,
            shape=obj.shape,
            friction=c.friction,
            world=obj.pose.matrix(),
            floor_z=None if table is None else table.height,
        )
        return (poses if to_tool is None else poses @ to_tool), columns
    d = None if obj is None else obj.dims
    poses = sources.generate(
        c.source,
        c.count,
        rng,
        shape=None if obj is None else obj.shape,
        radius=None if d is None else d.radius,
        height=None if d is None else d.height,
        size=None if d is None else d.size,
        depth=c.depth,
        rings=c.rings,
    )
    sources.add_noise(poses, c.noise.position, c.noise.angle_deg, rng)
    if to_tool is not None:  # generated grasps are mapped like imported ones
        poses = poses @ to_tool
    assert obj is not None
    return obj.pose.matrix() @ poses, {}


@takes_config
def generate_candidates(cfg: Config, *, report: dict[str, Any] | None = None) -> GraspTable:
    """The candidate grasp table of a config: ``dq`` (N, 8) and per-candidate columns.

    Args:
        cfg: The full config (``candidates``, ``object``, ``environment.table``, ``seed``).
        report: A dict that gets ``grasp_frame``, how a grasp file's gripper
            frame was mapped (:meth:`gcm_pipeline.sources.GripperChoice.as_dict`),
            when the file has one.

    Returns:
        A table with ``dq``: unit dual quaternions [rw, rx, ry, rz, dw, dx, dy, dz]
        of the grasp frame in the world, one row per candidate; for a grasp
        file also ``source_id`` (the row in the file) and the file's own
        columns (:func:`gcm_pipeline.sources.read_grasp_file`).

    Raises:
        ConfigError: A generator without a matching ``object`` section.
        InputError: An unreadable or invalid grasp file, a file whose gripper
            is unknown, or no grasp left.
    """
    poses, columns = candidate_poses(cfg, report)
    if poses.shape[0] == 0:
        raise InputError(f"candidates: no grasp left from {_describe_source(cfg.candidates)}")
    log.info("candidates: %d from %s", poses.shape[0], _describe_source(cfg.candidates))
    return GraspTable({"dq": dq_from_matrix(poses), **columns})


def _describe_source(c: CandidatesConfig) -> str:
    if c.source == "file":
        return f"file {c.path}"
    return f"generator {c.source!r}"


def input_files(cfg: Config) -> dict[str, Path]:
    """The files a config reads, keyed by their dotted config key.

    ``candidates.path``, ``object.mesh``, ``environment.obstacles.<i>.mesh``
    and ``robot.spec`` when it is a spec file rather than a shipped name.
    """
    files: dict[str, Path] = {}
    if cfg.candidates.path is not None:
        files["candidates.path"] = Path(cfg.candidates.path)
    if cfg.object is not None and cfg.object.mesh is not None:
        files["object.mesh"] = Path(cfg.object.mesh)
    for i, obstacle in enumerate(cfg.environment.obstacles):
        if obstacle.mesh is not None:
            files[f"environment.obstacles.{i}.mesh"] = Path(obstacle.mesh)
    spec = cfg.robot.spec
    if spec.endswith((".yaml", ".yml")) or "/" in spec:
        files["robot.spec"] = Path(spec)
    return files


@takes_config
def preflight(cfg: Config, *, viewer: bool = False) -> Robot:
    """Check, before any work, what the config refers to outside itself.

    ``gcm validate`` and ``gcm run`` (:meth:`Pipeline.run`) both call it:

    - every file the config reads exists (:func:`input_files`); relative
      paths were resolved against the config's folder;
    - ``robot.spec`` names a shipped spec or a valid spec file whose model
      exists; the robot is built (kinematics, locked joints inside their
      ranges, a readable SRDF, collision meshes that load);
    - the object and obstacle meshes load and have finite vertices;
    - with the live viewer requested (``viewer`` or ``publish.meshcat``) and a
      ``publish.zmq_url``, the meshcat server there answers within
      ``publish.connect_timeout_s``; without the viewer a ``zmq_url`` is unused,
      which is logged as a warning.

    Args:
        cfg: The config.
        viewer: The live viewer is requested (``gcm run --meshcat``).

    Returns:
        The robot (the run uses it).

    Raises:
        RobotSpecError: ``robot.spec: ...``, unknown robot or invalid spec.
        InputError: ``<key>: file not found: <path>``, or a mesh that does not load.
        PublishError: ``publish.zmq_url: ...``, no meshcat server answers there.
    """
    from gcm_pipeline.config.robot_spec import load_spec
    from gcm_pipeline.errors import InputError, PublishError, RobotSpecError
    from gcm_pipeline.geometry.shapes import shape_geometry
    from gcm_pipeline.robot.model import Robot

    for key, path in input_files(cfg).items():
        try:
            found, there = path.is_file(), path.exists()
        except (OSError, ValueError):
            found = there = False
        if not found:
            what = {"candidates.path": "grasp file", "robot.spec": "robot spec file"}.get(
                key, "mesh file"
            )
            if there:  # a directory, a device (/dev/zero), a pipe
                raise InputError(f"{key}: {what} {path} is not a regular file")
            raise InputError(
                f"{key}: {what} not found: {path} (relative paths resolve against the "
                "config's folder)"
            )
    try:
        robot = Robot(load_spec(cfg.robot.spec))
        robot.build_geometry("collision")
    except RobotSpecError as exc:
        raise type(exc)(f"robot.spec: {exc}") from exc
    shapes: list[tuple[str, Any]] = [("object", cfg.object)]
    shapes += [(f"environment.obstacles.{i}", o) for i, o in enumerate(cfg.environment.obstacles)]
    for where, shape in shapes:
        if shape is not None and shape.shape == "mesh":
            shape_geometry("mesh", shape.dims, mesh=shape.mesh, scale=shape.scale, where=where)
    pub = cfg.publish
    if pub.zmq_url is None:
        return robot
    if not (viewer or pub.meshcat):
        log.warning("publish.zmq_url is set but the live viewer is off; add --meshcat")
        return robot
    from gcm_pipeline.outputs.live import probe_server

    try:
        probe_server(pub.zmq_url, pub.connect_timeout_s)
    except PublishError as exc:
        raise PublishError(f"publish.zmq_url: {exc}") from exc
    return robot


@takes_config
def build_manifold(grasps: GraspTable, cfg: Config) -> Manifold:
    """Delaunay manifold over the candidates' chart (config section ``manifold``).

    The object pose (if the config has an ``object``) is the frame of the
    cylindrical and spherical charts.

    Args:
        grasps: The candidate table (``dq``).
        cfg: The full config.

    Returns:
        A :class:`gcm_pipeline.manifold.build.Manifold`.
    """
    from gcm_pipeline.manifold import build as stage

    m = cfg.manifold
    return stage.build_manifold(
        grasps,
        projection=m.projection,
        triangulator=m.triangulator,
        max_edge_length=m.max_edge_length,
        max_edge_angle_deg=m.max_edge_angle_deg,
        frame=cfg.object.pose.matrix() if cfg.object is not None else None,
    )


@takes_config
def densify(grasps: GraspTable, manifold: Manifold, cfg: Config) -> GraspTable:
    """Densify the manifold's triangles (config section ``densify``).

    Args:
        grasps: The candidate table; the manifold's triangles index its rows.
        manifold: From :func:`build_manifold`.
        cfg: The full config.

    Returns:
        All candidates (first, in input order) and the interpolated grasps,
        with ``dq, origin, triangle, vertices, weights``.
    """
    from gcm_pipeline.manifold import densify as stage

    d = cfg.densify
    return stage.densify(
        grasps,
        manifold,
        subdivisions=d.subdivisions,
        spacing=d.spacing,
        method=d.method,
        max_poses=d.max_poses,
    )


@takes_config
def refinement_score(robot: Robot, cfg: Config) -> Callable[[GraspTable], np.ndarray]:
    """The metric adaptive refinement follows: the ranking metric of ``cfg``.

    ``combined`` is normalised over the reachable rows checked so far;
    ``margin`` (which needs the finished manifold) falls back to Yoshikawa's
    index.
    """
    from gcm_pipeline.ranking import rank as ranking

    r = cfg.ranking
    return functools.partial(
        ranking.reachable_score, robot=robot, metric=r.metric, weights=r.weights
    )


@takes_config
def densify_adaptive(
    grasps: GraspTable,
    manifold: Manifold,
    robot: Robot,
    cfg: Config,
    *,
    check: ReachabilityCheck | None = None,
) -> GraspTable:
    """Densify where reachability or the metric changes, checking as it refines.

    Section ``densify.adaptive`` (see :mod:`gcm_pipeline.manifold.adaptive`);
    reachability is decided as in :func:`check_reachability`, so the result
    has the columns of densify and of the reachability stage, plus ``level``.

    Args:
        grasps: The candidate table; the manifold's triangles index its rows.
        manifold: From :func:`build_manifold`.
        robot: From :func:`robot_from_config`.
        cfg: The full config (``densify.adaptive`` set).
        check: A :class:`ReachabilityCheck` to use (its ``solved`` counts the IK solves).

    Raises:
        ConfigError: No ``densify.adaptive`` section, or the table would grow
            beyond ``densify.max_poses``.
    """
    from gcm_pipeline.errors import ConfigError
    from gcm_pipeline.manifold import adaptive as stage

    a = cfg.densify.adaptive
    if a is None:
        raise ConfigError("densify_adaptive needs a densify.adaptive section")
    own = check is None
    check = ReachabilityCheck(robot, cfg) if check is None else check
    try:
        return stage.refine(
            grasps,
            manifold,
            check,
            max_level=a.max_level,
            min_level=a.min_level,
            criteria=a.refine,
            score=refinement_score(robot, cfg) if "metric" in a.refine else None,
            metric_threshold=a.metric_threshold,
            method=cfg.densify.method,
            max_poses=cfg.densify.max_poses,
        )
    finally:
        if own:
            check.close()


@takes_config
def adaptive_counts(grasps: GraspTable, manifold: Manifold, cfg: Config) -> dict[str, int]:
    """``counts["adaptive"]`` of a run: IK solves, rows per level, the uniform lattice's size.

    Keys: ``max_level``, ``ik_solves``, ``level_0`` .. ``level_L`` (rows first
    made at each level), ``uniform_subdivisions`` and ``uniform_rows`` (the
    uniform lattice with ``2**max_level`` subdivisions).
    """
    from gcm_pipeline.manifold.adaptive import uniform_size

    a = cfg.densify.adaptive
    assert a is not None
    levels, per_level = np.unique(np.asarray(grasps["level"]), return_counts=True)
    out = {"max_level": a.max_level, "ik_solves": len(grasps)}
    out.update({f"level_{k}": int(v) for k, v in zip(levels, per_level, strict=True)})
    out["uniform_subdivisions"] = 1 << a.max_level
    out["uniform_rows"] = uniform_size(manifold.triangles, manifold.n_vertices, a.max_level)
    return out


@takes_config
def add_continuity(
    grasps: GraspTable,
    manifold: Manifold,
    cfg: Config,
    *,
    check: ReachabilityCheck | None = None,
) -> tuple[GraspTable, dict[str, int]]:
    """IK continuity and the robustness margin (sections ``continuity``, ``manifold``).

    Adds ``ik_jump`` [rad] and ``patch`` (:mod:`gcm_pipeline.manifold.continuity`)
    and ``margin`` [m] (:mod:`gcm_pipeline.manifold.margin`); with
    ``continuity.reseed`` first re-solves border grasps of smaller patches from
    their neighbours in larger ones (that needs ``check``, or the robot to
    build one).

    Returns:
        The table and ``counts["continuity"]``: ``patches`` and, with
        re-seeding, ``patches_before_reseed``, ``reseeded`` (grasps that took a
        new solution) and ``reseed_ik_solves``.
    """
    from gcm_pipeline.manifold import continuity as stage
    from gcm_pipeline.manifold.lattice import row_mesh
    from gcm_pipeline.manifold.margin import margin

    c = cfg.continuity
    edges = row_mesh(grasps, manifold.triangles, manifold.n_vertices).edges
    counts: dict[str, int] = {}
    if c.reseed:
        own = check is None
        check = ReachabilityCheck(robot_from_config(cfg), cfg) if check is None else check
        try:
            grasps, report = stage.reseed(
                grasps, edges, check, threshold=c.threshold, max_rounds=c.max_rounds
            )
        finally:
            if own:
                check.close()
        counts.update(
            patches_before_reseed=report.patches_before,
            reseeded=report.moved,
            reseed_ik_solves=report.solved,
        )
    cols = stage.continuity_columns(grasps, edges, c.threshold)
    counts = {"patches": int(cols["patch"].max(initial=-1) + 1), **counts}
    cols["margin"] = margin(
        np.asarray(grasps["dq"], dtype=np.float64),
        np.asarray(grasps["reachable"], dtype=bool),
        edges,
        cfg.manifold.orientation_scale,
    )
    return grasps.with_columns(**cols), counts


@takes_config
def branch_scores(grasps: GraspTable, robot: Robot, cfg: Config) -> np.ndarray:
    """The ranking metric of every IK branch (N, K) (``solutions`` column), higher is better.

    ``combined`` normalises each metric over all branches of all reachable
    grasps; ``margin`` is the same for every branch of a grasp, so branches are
    compared by Yoshikawa's index instead (also its weight in ``combined`` is
    left out).
    """
    from gcm_pipeline.ranking import rank as ranking

    clearance = grasps["solutions_clearance"] if "solutions_clearance" in grasps else None
    r = cfg.ranking
    return ranking.branch_scores(
        grasps["solutions"], robot, metric=r.metric, weights=r.weights, clearance=clearance
    )


@takes_config
def select_branches(
    grasps: GraspTable, manifold: Manifold, robot: Robot, cfg: Config
) -> GraspTable:
    """Choose one IK branch per grasp (``ik.select``; needs ``ik.solutions`` > 1).

    See :mod:`gcm_pipeline.reach.branches`. A table without branch columns is
    returned unchanged.
    """
    from gcm_pipeline.manifold.lattice import row_mesh
    from gcm_pipeline.reach import branches as stage

    if "solutions" not in grasps:
        return grasps
    edges = row_mesh(grasps, manifold.triangles, manifold.n_vertices).edges
    return stage.select_branches(
        grasps,
        edges,
        branch_scores(grasps, robot, cfg),
        method=cfg.ik.select,
        threshold=cfg.continuity.threshold,
    )


@takes_config
def robot_from_config(cfg: Config) -> Robot:
    """The robot of ``cfg.robot.spec`` (a shipped name or a spec YAML path)."""
    from gcm_pipeline.config.robot_spec import load_robot as _load

    return _load(cfg.robot.spec)


#: The same as :func:`robot_from_config` (``gcm_pipeline.load_robot`` is the
#: one of :mod:`gcm_pipeline.config.robot_spec`, by name or path).
load_robot = robot_from_config


def collision_world(
    environment: EnvironmentConfig | None = None,
    object_cfg: ObjectConfig | None = None,
    base_pose: Pose | np.ndarray | None = None,
) -> list[WorldShape]:
    """The collision world of the config sections, in the robot's base frame.

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
    from gcm_pipeline.config import EnvironmentConfig
    from gcm_pipeline.robot import collision

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
) -> CollisionChecker:
    """The collision checker of a run (``environment``, ``object``, ``robot.base_pose``).

    Args:
        robot: The robot.
        environment: Config section (None: the default, a table at z = 0).
        object_cfg: Config ``object`` section or None.
        base_pose: Robot base in the world (Pose or (4, 4)); None: identity.
        threads: Threads for the batched checks.

    Returns:
        The :class:`~gcm_pipeline.robot.collision.CollisionChecker`; a world
        shape overlapping the robot's fixed links is logged as a warning.
    """
    from gcm_pipeline.config import EnvironmentConfig
    from gcm_pipeline.robot.collision import CollisionChecker

    env = EnvironmentConfig() if environment is None else environment
    checker = CollisionChecker(
        robot,
        collision_world(env, object_cfg, base_pose),
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


def approach_move(approach: ApproachConfig | None) -> Move | None:
    """The ``approach`` section as a :class:`Move` (backwards along the grasp frame's z)."""
    from gcm_pipeline.reach.moves import Move

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
    from gcm_pipeline.reach.moves import Move

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
    from gcm_pipeline.reach.options import ReachOptions

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
def reachability_engine(robot: Robot, cfg: Config) -> ReachabilityEngine:
    """The reachability engine of a config.

    Reads ``ik``, ``environment``, ``object``, ``approach``, ``retreat``,
    ``robot.base_pose`` and ``seed`` (:func:`reach_options`; the
    ``environment`` and ``object`` sections become the collision checker).
    Build it once to check many pose sets with the same robot, seed library and
    collision world (:func:`check_reachability` with ``engine=``); close it (or
    use a ``with`` block) to stop its worker processes.
    """
    from gcm_pipeline.reach import check as stage

    options = reach_options(cfg)
    checker = None
    if cfg.environment is not None or cfg.object is not None:
        checker = make_checker(robot, cfg.environment, cfg.object, options.base_pose)
    return stage.make_engine(robot, options, checker=checker)


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
            reuse one across calls (default: built for this call and closed).

    Returns:
        The table with ``reachable, reason, q, pos_err, rot_err``,
        ``q_pregrasp, q_retreat, q_rejected`` (and ``clearance``) added.
    """
    from gcm_pipeline.reach import check as stage

    own = engine is None
    eng = reachability_engine(robot, cfg) if engine is None else engine
    try:
        done = stage.check_reachability(
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

    def __call__(self, dq: np.ndarray, seeds: np.ndarray | None = None) -> GraspTable:
        """Check poses (M, 8) (world) with optional warm starts (M, K, nq) [rad].

        Returns:
            A table of M rows: ``dq, reachable, reason, q, pos_err, rot_err``
            (and ``clearance`` with collisions), as the reachability stage.
        """
        from gcm_pipeline.reach import check as stage

        cfg = self.config
        dq = np.asarray(dq, dtype=np.float64).reshape(-1, 8)
        table = GraspTable({"dq": dq})
        if not len(dq):
            return _empty_reachability(
                table, self.robot.nq, with_clearance=self.engine.checker is not None
            )
        done = stage.check_reachability(
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


@takes_config
def rank(grasps: GraspTable, robot: Robot, cfg: Config) -> GraspTable:
    """Manipulability metrics and ranks of the reachable grasps (``ranking``).

    See :func:`gcm_pipeline.ranking.rank.rank`; the ``clearance`` and
    ``combined`` metrics need the ``clearance`` column of the collision checks.

    Returns:
        The table with ``manipulability`` (and the other metric columns),
        ``rank`` (1-based among reachable grasps, 0 for unreachable) and
        ``top`` added.
    """
    from gcm_pipeline.ranking import rank as stage

    r = cfg.ranking
    return stage.rank(grasps, robot, metric=r.metric, top_k=r.top_k, weights=r.weights)


@takes_config
def publish(result: RunResult, cfg: Config, out_dir: str | Path) -> list[Path]:
    """Write ``scene.html`` / PNG plots into ``out_dir`` (section ``publish``).

    Returns:
        The files written.
    """
    from gcm_pipeline.outputs import html

    counts = {k: v for k, v in result.counts.items() if isinstance(v, int)}
    files = html.publish(
        result.grasps, result.manifold, result.robot, cfg, Path(out_dir), counts=counts
    )
    return list(files)


def top_grasps(grasps: GraspTable, n: int, metric: str = "yoshikawa") -> list[dict[str, Any]]:
    """The ``n`` best-ranked grasps as plain dicts (rank, pose, metrics, q).

    Each has ``rank, row, origin, x, y, z, qw, qx, qy, qz`` (``qw >= 0``),
    ``manipulability``, the ranking metric's column when it is another one,
    and ``q``. Rows without a ``rank`` column, or unranked (rank 0), are left out.
    """
    from gcm_pipeline.ranking.metrics import METRIC_COLUMNS

    if "rank" not in grasps or n <= 0:
        return []
    rank_col = np.asarray(grasps["rank"])
    rows = np.flatnonzero(rank_col > 0)
    rows = rows[np.argsort(rank_col[rows], kind="stable")][:n]
    if rows.size == 0:
        return []
    pos, quat = dq_to_pos_quat(grasps["dq"][rows])
    quat = np.where(quat[:, :1] < 0, -quat, quat)
    out = []
    for k, i in enumerate(rows.tolist()):
        item: dict[str, Any] = {"rank": int(rank_col[i]), "row": i}
        if "origin" in grasps:
            item["origin"] = str(grasps["origin"][i])
        item.update(zip(("x", "y", "z"), pos[k].tolist(), strict=True))
        item.update(zip(("qw", "qx", "qy", "qz"), quat[k].tolist(), strict=True))
        for name in dict.fromkeys(("manipulability", METRIC_COLUMNS.get(metric, metric))):
            if name in grasps:
                item[name] = float(grasps[name][i])
        if "q" in grasps:
            item["q"] = np.asarray(grasps["q"][i], dtype=float).tolist()
        out.append(item)
    return out


@dataclass(frozen=True)
class ConfigRunQueries:
    """A run's config as the manifold queries take it (a :class:`~.manifold.query.RunQueries`).

    Args:
        config: The run's config.
    """

    config: Config

    @property
    def ranking_metric(self) -> str:
        """``ranking.metric``."""
        return self.config.ranking.metric

    @property
    def combined_weights(self) -> Mapping[str, float]:
        """``ranking.weights``, else the default weights of the ``combined`` metric."""
        from gcm_pipeline.ranking.metrics import DEFAULT_COMBINED_WEIGHTS

        return self.config.ranking.weights or DEFAULT_COMBINED_WEIGHTS

    def load_robot(self) -> Robot:
        """The robot of ``robot.spec``."""
        return robot_from_config(self.config)

    def reachability(self, robot: Robot, cfg: Config) -> ReachabilityCheck:
        """A :class:`ReachabilityCheck` of ``robot`` with ``cfg``."""
        return ReachabilityCheck(robot, cfg)

    def robot_metrics(self, robot: Robot, q: np.ndarray) -> Mapping[str, np.ndarray]:
        """The manipulability metrics of configurations ``q`` (N, nq) [rad]."""
        from gcm_pipeline.robot.manipulability import manipulability_metrics

        return manipulability_metrics(robot, q)


def grasp_manifold(
    manifold: Manifold, grasps: GraspTable, cfg: Config, robot: Robot | None = None
) -> GraspManifold:
    """The queryable manifold of a run: its triangles and grasp table, queried as ``cfg`` says.

    ``densify.method`` is the blend, ``manifold.orientation_scale`` the pose
    metric's ``L``; reachability, robot metrics and ranking weights come from
    the rest of ``cfg`` (:class:`ConfigRunQueries`).
    """
    from gcm_pipeline.manifold.query import GraspManifold

    return GraspManifold(
        manifold,
        grasps,
        method=cfg.densify.method,
        run=ConfigRunQueries(cfg),
        robot=robot,
        orientation_scale=cfg.manifold.orientation_scale,
    )


def load_manifold(run_dir: str | Path) -> GraspManifold:
    """Load the queryable manifold of a run directory (``gcm run`` output).

    Reads ``grasps.csv``, ``manifold.npz``, ``summary.json`` and
    ``config.yaml`` (the blend method, the robot and what decides
    reachability).

    Raises:
        InputError: Not a run directory, or a file in it is missing or unreadable.
        ConfigError: Its ``config.yaml`` is invalid.
    """
    from gcm_pipeline.errors import InputError

    run = run_files.read_run(run_dir)
    path = Path(run_dir) / "config.yaml"
    if not path.is_file():
        raise InputError(f"not a run directory: {run_dir} lacks config.yaml")
    return grasp_manifold(run.manifold, run.grasps, load_config(path))


@dataclass
class RunResult:
    """What a pipeline run produced.

    Attributes:
        grasps: The final grasp table (candidates first, then interpolated;
            with reachability and ranking columns).
        manifold: The manifold (triangles over candidate row ids).
        robot: The robot model used.
        counts: ``candidates, triangles, triangles_dropped, dropped_by_reason``
            (dict), ``densified, interpolated, reachable, unreachable_by_reason``
            (dict: reason -> count).
        timings: Seconds per stage, in run order.
        config: The resolved config.
        run_dir: The run directory, or None when nothing was written.
        grasp_manifold: The manifold as a queryable
            :class:`~gcm_pipeline.manifold.query.GraspManifold` (built on first use).
        grasp_frame: How a grasp file's gripper frame was mapped onto the
            robot's grasp frame (``format``, ``gripper``, ``chosen_by``,
            ``file_gripper``, ``describe``), None for other sources.
    """

    grasps: GraspTable
    manifold: Manifold
    robot: Robot
    counts: dict[str, Any]
    timings: dict[str, float]
    config: Config
    run_dir: Path | None = None
    files: list[Path] = field(default_factory=list)
    grasp_frame: dict[str, Any] | None = None

    @functools.cached_property
    def grasp_manifold(self) -> GraspManifold:
        """The run's manifold as a queryable object (sample, locate, nearest reachable, best).

        See :class:`gcm_pipeline.manifold.query.GraspManifold`; the same as
        :func:`gcm_pipeline.load_manifold` on the run directory.
        """
        return grasp_manifold(self.manifold, self.grasps, self.config, self.robot)

    def top(self, n: int | None = None) -> list[dict[str, Any]]:
        """The best-ranked grasps (default: ``ranking.top_k`` of them)."""
        r = self.config.ranking
        return top_grasps(self.grasps, r.top_k if n is None else n, r.metric)

    def summary(self) -> dict[str, Any]:
        """The content of ``summary.json``.

        ``legend`` is the colour scale of the scene and the plots: the
        colormap, the manipulability range it spans and the colour and count
        of every unreachable reason.
        """
        from gcm_pipeline.outputs.scene import legend

        return {
            "counts": dict(self.counts),
            "timings_s": {k: round(v, 6) for k, v in self.timings.items()},
            "ranking": {"metric": self.config.ranking.metric, "top": self.top()},
            **({"grasp_frame": self.grasp_frame} if self.grasp_frame else {}),
            "legend": legend(self.grasps),
            "config": self.config.to_dict(),
            "versions": run_files.versions(),
        }

    def __repr__(self) -> str:
        c = self.counts
        total = sum(self.timings.values())
        return (
            f"RunResult(candidates={c.get('candidates')}, triangles={c.get('triangles')} "
            f"(+{c.get('triangles_dropped')} dropped), densified={c.get('densified')}, "
            f"reachable={c.get('reachable')}, metric={self.config.ranking.metric!r}, "
            f"time={total:.2f}s, run_dir={str(self.run_dir) if self.run_dir else None!r})"
        )


#: The steps of a run, in order (the progress bar, the timings and the order of
#: :meth:`Pipeline.run` all follow this one list; the last two write the run directory).
STEPS = (
    "candidates",
    "manifold",
    "densify",
    "robot",
    "reachability",
    "continuity",
    "ranking",
    "write",
    "publish",
)
WRITE_STEPS = ("write", "publish")


class Pipeline:
    """Runs every stage of a config in order.

    Example:
        >>> result = Pipeline.from_yaml("configs/bottle_side.yaml").run("results/bottle")
        >>> result.counts["reachable"]  # doctest: +SKIP

    Args:
        config: The validated config.
    """

    def __init__(self, config: Config, *, source: str | Path | None = None) -> None:
        if not isinstance(config, Config):
            raise TypeError(f"Pipeline needs a Config, got {type(config).__name__}")
        self.config = config
        #: The config file (from :meth:`from_yaml`); a run never replaces its folder.
        self.source = Path(source).absolute() if source is not None else None

    @classmethod
    def from_yaml(cls, path: str | Path, overrides: Iterable[str] | str = ()) -> Pipeline:
        """Load a YAML config with ``key=value`` overrides (or one as a string); see load_config."""
        over = (overrides,) if isinstance(overrides, str) else tuple(overrides)
        return cls(load_config(path, over), source=path)

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> Pipeline:
        """Validate a plain dict into a config, see :meth:`Config.from_dict`."""
        return cls(Config.from_dict(dict(data)))

    def __repr__(self) -> str:
        c = self.config
        return (
            f"Pipeline(source={c.candidates.source!r}, robot={c.robot.spec!r}, "
            f"projection={c.manifold.projection!r}, ik={c.ik.backend!r}, "
            f"metric={c.ranking.metric!r}, out={str(c.output.dir)!r})"
        )

    def run(
        self,
        out_dir: str | Path | None = None,
        progress: bool = True,
        *,
        force: bool = False,
        write: bool = True,
        viewer: bool = False,
        robot: Robot | None = None,
    ) -> RunResult:
        """Run every stage and write the run directory.

        Args:
            out_dir: The run directory (default: ``output.dir``, relative to
                the working directory).
            progress: Show progress bars on the slow stages.
            force: Replace an existing previous run directory (one with
                ``summary.json`` and ``grasps.csv``; only at the end, when the
                new one is complete). Other non-empty directories, the working
                directory, its parents and the config's folder are never
                replaced; an empty directory is used without ``force``.
            write: Write the run directory (False: only return the result).
            viewer: The caller opens the live viewer afterwards (``gcm run
                --meshcat``): a ``publish.zmq_url`` server is probed first.
            robot: The robot of ``robot.spec``, built before by the caller, who
                also did the :func:`preflight`: a placement study runs many
                configs on one robot and its caches (seed library, geometry).
                None: :func:`preflight` checks the config and builds it.

        Returns:
            The result; ``run_dir`` is the directory written (or None).

        Raises:
            GcmError: A user error (config, input, output path, robot spec);
                checked before any work where possible. Nothing is left
                behind on failure.
        """
        cfg = self.config
        out = Path(out_dir) if out_dir is not None else Path(cfg.output.dir)
        keep = self._inputs()
        # what the config refers to first: a bad robot spec is not hidden behind "--force"
        t0 = time.perf_counter()
        if robot is None:
            robot = preflight(cfg, viewer=viewer)  # builds the robot: the "robot" stage's work
        robot_s = time.perf_counter() - t0
        if write:
            out = transaction.check_output_dir(out, force=force, keep=keep)
        timings: dict[str, float] = {}
        names = [n for n in STEPS if write or n not in WRITE_STEPS]
        expected = iter(names)
        # one bar over the stages (the slow ones, IK and publishing, take seconds);
        # tqdm hides it when stderr is not a terminal
        bar = tqdm(
            total=len(names), desc="gcm", unit="stage", leave=False, disable=not progress or None
        )

        @contextmanager
        def stage(name: str) -> Iterator[None]:
            # the steps run in the order of STEPS, each once: the one list
            step = next(expected, None)
            if step != name:
                raise RuntimeError(f"pipeline step {name!r} runs where STEPS has {step!r}")
            t0 = time.perf_counter()
            log.debug("stage %s ...", name)
            bar.set_postfix_str(name)
            yield
            timings[name] = time.perf_counter() - t0
            bar.update(1)
            log.info("stage %-12s %8.3f s", name, timings[name])

        try:
            return self._run(
                out, stage, timings, robot, robot_s, force=force, write=write, progress=progress
            )
        finally:
            bar.close()

    def _inputs(self) -> list[Path]:
        """The config file and the files it reads: a run never replaces their folder."""
        files = list(input_files(self.config).values())
        return files if self.source is None else [self.source, *files]

    def _run(
        self,
        out: Path,
        stage: Callable[[str], AbstractContextManager[None]],
        timings: dict[str, float],
        robot: Robot,
        robot_s: float,
        *,
        force: bool,
        write: bool,
        progress: bool,
    ) -> RunResult:
        cfg = self.config
        source: dict[str, Any] = {}
        with stage("candidates"):
            candidates = generate_candidates(cfg, report=source)
        with stage("manifold"):
            manifold = build_manifold(candidates, cfg)
        adaptive = cfg.densify.adaptive is not None
        check: ReachabilityCheck | None = None
        with stage("densify"):
            if not adaptive:  # adaptive densification solves as it refines, below
                grasps = densify(candidates, manifold, cfg)
        with stage("robot"):
            pass  # built by preflight
        timings["robot"] = robot_s
        try:
            with stage("reachability"):
                if adaptive:
                    check = ReachabilityCheck(robot, cfg)
                    grasps = densify_adaptive(candidates, manifold, robot, cfg, check=check)
                else:
                    grasps = check_reachability(grasps, robot, cfg, progress=progress)
                grasps = select_branches(grasps, manifold, robot, cfg)
            unreachable = _count_by(grasps["reason"][~np.asarray(grasps["reachable"], dtype=bool)])
            log.info(
                "reachable %d/%d%s",
                len(grasps) - sum(unreachable.values()),
                len(grasps),
                " (unreachable: " + ", ".join(f"{k} {v}" for k, v in unreachable.items()) + ")"
                if unreachable
                else "",
            )
            with stage("continuity"):
                if cfg.continuity.reseed and check is None:
                    check = ReachabilityCheck(robot, cfg)
                grasps, continuity = add_continuity(grasps, manifold, cfg, check=check)
        finally:
            if check is not None:
                check.close()
        with stage("ranking"):
            grasps = rank(grasps, robot, cfg)
        counts = {
            "candidates": len(candidates),
            "triangles": int(len(manifold.triangles)),
            "triangles_dropped": int(len(manifold.dropped)),
            "dropped_by_reason": _count_by(manifold.dropped_reason),
            "densified": len(grasps),
            "interpolated": len(grasps) - len(candidates),
            "reachable": int(np.count_nonzero(grasps["reachable"])),
            "unreachable_by_reason": unreachable,
        }
        _warn_empty(counts, cfg)
        if adaptive:
            counts["adaptive"] = adaptive_counts(grasps, manifold, cfg)
        counts["continuity"] = continuity
        result = RunResult(grasps, manifold, robot, counts, timings, cfg)
        result.grasp_frame = source.get("grasp_frame")
        if not write:
            return result
        with transaction.atomic_run_dir(out, force=force, keep=self._inputs()) as tmp:
            with stage("write"):
                run_files.write_run_files(tmp, grasps, manifold, cfg.to_dict())
            with stage("publish"):
                published = publish(result, cfg, tmp)
            run_files.write_summary(result.summary(), tmp / "summary.json")
        result.run_dir = out
        result.files = sorted(p for p in out.iterdir() if p.name != transaction.MARKER)
        log.info("run directory %s (%d published files)", out, len(published))
        return result


def _warn_empty(counts: Mapping[str, Any], cfg: Config) -> None:
    """Warn about a run that produced nothing to look at (no triangle, no reachable grasp)."""
    if counts["triangles"] == 0:
        dropped = counts["dropped_by_reason"]
        why = ", ".join(f"{k} {v}" for k, v in dropped.items())
        log.warning(
            "no triangle is left%s, so no grasp was interpolated; raise "
            "manifold.max_edge_length / manifold.max_edge_angle_deg or try another "
            "manifold.projection",
            f" (dropped: {why})" if why else "",
        )
    if counts["reachable"] == 0 and counts["densified"]:
        log.warning("%s", unreachable_hint(counts["unreachable_by_reason"]))


#: What to try when most grasps fail for a reason (see :func:`unreachable_hint`).
_HINTS = {
    "out_of_reach": "the grasps lie beyond the arm's reach: move the object (object.pose) "
    "or the robot (robot.base_pose) closer",
    "no_ik": "no IK solution: these grasp orientations may be impossible for this arm here; "
    "try another robot.base_pose or grasps approached from other sides",
    "joint_limits": "the solutions leave the joint limits: check the robot spec's joint_limits "
    "and limit_margin",
    "collision_object": "the robot hits the object at the grasp: is the grasp frame the "
    "robot's TCP? An arm without a hand needs a tool in its robot spec (see ur5.yaml), or map "
    "the grasps onto its grasp frame with candidates.grasp_to_tool; "
    "environment.contact_tolerance sets how deep the gripper may touch",
    "collision_environment": "the arm hits the table or an obstacle: check "
    "environment.table.height and the object's pose",
    "collision_self": "every solution collides with the arm itself: try grasps approached "
    "from other sides or another robot.base_pose",
    "approach": "the pre-grasp approach fails: shorten approach.distance or turn it off "
    "(approach: null)",
    "retreat": "the post-grasp retreat fails: shorten retreat.distance or turn it off "
    "(retreat: null)",
}


def unreachable_hint(unreachable: Mapping[str, int]) -> str:
    """Why no grasp is reachable and what to try, in one line.

    Args:
        unreachable: Unreachable grasps by reason, most frequent first (the
            run's ``counts["unreachable_by_reason"]``).

    Returns:
        ``"no grasp is reachable (r1 n1, r2 n2, ...); try: ..."``: every
        reason with its count, and what to try for the two most frequent.
    """
    reasons = ", ".join(f"{k} {v}" for k, v in unreachable.items()) or "no reason recorded"
    tips = [_HINTS[k] for k in list(unreachable)[:2] if k in _HINTS]
    tip = "; ".join(tips) or "check robot.base_pose, the object pose and the environment"
    return f"no grasp is reachable ({reasons}); try: {tip}"


def _count_by(labels: Any) -> dict[str, int]:
    """How often each label occurs, most frequent first (ties by name)."""
    names, n = np.unique(np.asarray(labels, dtype=str).reshape(-1), return_counts=True)
    pairs = sorted(zip(names.tolist(), n.tolist(), strict=True), key=lambda p: (-p[1], p[0]))
    return {str(k): int(v) for k, v in pairs}
