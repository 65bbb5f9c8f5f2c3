"""The ``candidates`` step: a config's grasp source (file, generator, sampler) as a table."""

from __future__ import annotations

import logging
from typing import Any

import numpy as np

from gcm_pipeline.config.gripper_spec import gripper_registry, load_gripper
from gcm_pipeline.config.run import Config, takes_config
from gcm_pipeline.config.sections import CandidatesConfig
from gcm_pipeline.errors import ConfigError, InputError
from gcm_pipeline.geometry.dualquat import dq_from_matrix
from gcm_pipeline.sources.antipodal import antipodal_candidates, object_mesh
from gcm_pipeline.sources.files import file_format, read_grasps, to_grasp_frame
from gcm_pipeline.sources.files.contact_graspnet import CONTACT_COLUMNS
from gcm_pipeline.sources.generators import add_noise, generate
from gcm_pipeline.sources.grippers import GripperSpec
from gcm_pipeline.table import GraspTable

log = logging.getLogger(__name__)


def candidate_poses(
    cfg: Config, report: dict[str, Any] | None = None
) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    """World poses (N, 4, 4) of the grasp frame and per-candidate columns: ``candidates`` -> source.

    A file's poses go onto the grasp frame (:func:`~gcm_pipeline.sources.files.to_grasp_frame`)
    and into the world by ``candidates.camera_pose``, else by the object pose for
    ``frame: object``; generated and sampled grasps are mapped by ``grasp_to_tool``
    (on the right) and the object pose. ``report`` gets ``grasp_frame`` when a
    file's gripper frame was mapped.
    """
    c, obj = cfg.candidates, cfg.object
    to_tool = None if c.grasp_to_tool is None else c.grasp_to_tool.matrix()
    if c.source == "file":
        assert c.path is not None
        fmt = file_format(c.path, c.format)
        grasps = read_grasps(
            c.path,
            fmt,
            success_only=c.success_only,
            min_score=c.min_score,
            limit=c.limit,
            max_count=c.max_count,
        )
        filtered = grasps.selection.kept < grasps.selection.read
        if report is not None and (filtered or c.min_score is not None or c.limit is not None):
            report["selection"] = grasps.selection.as_dict()
        configured = None if c.gripper is None else load_gripper(c.gripper)
        poses, choice = to_grasp_frame(
            grasps,
            c.path,
            fmt,
            gripper=configured,
            grasp_to_tool=to_tool,
            registry=gripper_registry(),
            tool=None if cfg.robot.tool is None else load_gripper(cfg.robot.tool, "robot.tool"),
        )
        if choice is not None and report is not None:
            report["grasp_frame"] = choice.as_dict() | {"describe": choice.describe()}
        to_world = None
        if c.camera_pose is not None:
            to_world = c.camera_pose.matrix()
        elif c.frame == "object":
            if obj is None:
                raise ConfigError("candidates.frame 'object' needs an 'object' section")
            to_world = obj.pose.matrix()
        if to_world is None:
            return poses, grasps.columns
        return to_world @ poses, _move_contacts(grasps.columns, to_world)
    rng = np.random.default_rng(c.seed if c.seed is not None else cfg.seed)
    if c.source == "antipodal":
        if obj is None:
            raise ConfigError("candidates.source 'antipodal' samples an object: add 'object'")
        gripper = sampler_gripper(cfg)
        d = obj.dims
        mesh = object_mesh(
            obj.shape, radius=d.radius, height=d.height, size=d.size, mesh=obj.mesh, scale=obj.scale
        )
        table = cfg.environment.table
        poses, columns = antipodal_candidates(
            mesh,
            c.count,
            gripper,
            rng,
            shape=obj.shape,
            friction=c.friction,
            world=obj.pose.matrix(),
            floor_z=None if table is None else table.height,
        )
        if c.min_score is not None:
            keep = columns["score"] >= c.min_score
            log.info(
                "candidates: min_score %g keeps %d of %d sampled grasps",
                *(c.min_score, np.count_nonzero(keep), len(keep)),
            )
            poses, columns = poses[keep], {k: v[keep] for k, v in columns.items()}
        return (poses if to_tool is None else poses @ to_tool), columns
    d = None if obj is None else obj.dims
    poses = generate(
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
    add_noise(poses, c.noise.position, c.noise.angle_deg, rng)
    if to_tool is not None:  # generated grasps are mapped like imported ones
        poses = poses @ to_tool
    assert obj is not None
    return obj.pose.matrix() @ poses, {}


def sampler_gripper(cfg: Config) -> GripperSpec:
    """The antipodal sampler's hand: ``candidates.gripper``, else ``robot.tool``, else the Panda's.

    Raises:
        ConfigError: ``candidates.gripper`` and ``robot.tool`` name different
            grippers (grasps sampled for one hand, checked with another).
    """
    c, tool = cfg.candidates, cfg.robot.tool
    if c.gripper is not None and tool is not None:
        sampled, mounted = load_gripper(c.gripper), load_gripper(tool, "robot.tool")
        if (sampled.name, sampled.path) != (mounted.name, mounted.path):
            raise ConfigError(
                f"candidates.gripper: {c.gripper!r} samples grasps for another hand than the "
                f"robot carries (robot.tool {tool!r}); drop candidates.gripper to sample for "
                "the robot's tool",
                key="candidates.gripper",
                value=c.gripper,
            )
    if c.gripper is not None:
        return load_gripper(c.gripper)
    if tool is not None:
        return load_gripper(tool, "robot.tool")
    return load_gripper("franka_panda")


def _move_contacts(columns: dict[str, np.ndarray], pose: np.ndarray) -> dict[str, np.ndarray]:
    """``columns`` with the contact point (``contact_x/y/z``) moved by ``pose`` like the grasps."""
    if not all(k in columns for k in CONTACT_COLUMNS):
        return columns
    pts = np.column_stack([columns[k] for k in CONTACT_COLUMNS]) @ pose[:3, :3].T + pose[:3, 3]
    return columns | dict(zip(CONTACT_COLUMNS, pts.T, strict=True))


@takes_config
def generate_candidates(cfg: Config, *, report: dict[str, Any] | None = None) -> GraspTable:
    """The candidate grasp table of a config: ``dq`` (N, 8) and per-candidate columns.

    Args:
        cfg: The full config (``candidates``, ``object``, ``environment.table``, ``seed``).
        report: A dict that gets ``grasp_frame``, how a grasp file's gripper
            frame was mapped (:meth:`gcm_pipeline.sources.grippers.GripperChoice.as_dict`),
            when the file has one.

    Returns:
        A table with ``dq``: unit dual quaternions [rw, rx, ry, rz, dw, dx, dy, dz]
        of the grasp frame in the world, one row per candidate; for a grasp
        file also ``source_id`` (the row in the file) and the file's own
        columns (:func:`gcm_pipeline.sources.files.read_grasp_file`).

    Raises:
        ConfigError: A generator without a matching ``object`` section.
        InputError: An unreadable or invalid grasp file, a file whose gripper
            is unknown, or no grasp left.
    """
    poses, columns = candidate_poses(cfg, report)
    if poses.shape[0] == 0:
        raise InputError(f"candidates: no grasp left from {_describe_source(cfg.candidates)}")
    _check_score_metric(cfg, columns)
    log.info("candidates: %d from %s", poses.shape[0], _describe_source(cfg.candidates))
    return GraspTable({"dq": dq_from_matrix(poses), **columns})


def _describe_source(c: CandidatesConfig) -> str:
    if c.source == "file":
        return f"file {c.path}"
    return f"generator {c.source!r}"


def _check_score_metric(cfg: Config, columns: dict[str, np.ndarray]) -> None:
    """Refuse ranking by ``score`` (``ranking.metric``, a ``combined`` weight) without one."""
    r = cfg.ranking
    key = "ranking.metric" if r.metric == "score" else None
    if r.metric == "combined" and (r.weights or {}).get("score", 0) > 0:
        key = "ranking.weights.score"
    if key is None or "score" in columns:
        return
    raise ConfigError(
        f"{key}: 'score' ranks by the source's grasp quality, but "
        f"{_describe_source(cfg.candidates)} gives none (a grasp file's score, "
        "or source 'antipodal'); choose another metric",
        key=key,
        value="score",
    )
