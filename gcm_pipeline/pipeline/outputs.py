"""The ``publish`` step and exports: a config onto the options of :mod:`gcm_pipeline.outputs`.

Also the best grasps of a run as plain dicts.
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from gcm_pipeline.config.gripper_spec import gripper_registry, load_gripper
from gcm_pipeline.config.reach_sections import ObstacleConfig, TableConfig
from gcm_pipeline.config.robot_spec import load_robot, load_spec
from gcm_pipeline.config.run import Config, load_config, takes_config
from gcm_pipeline.config.sections import ObjectConfig
from gcm_pipeline.geometry.clouds import PointCloud
from gcm_pipeline.geometry.dualquat import dq_to_pos_quat
from gcm_pipeline.outputs import export, html, live
from gcm_pipeline.outputs.export import ExportResult, MoveItOptions
from gcm_pipeline.outputs.scene import PublishOptions, SceneOptions
from gcm_pipeline.outputs.scene_cloud import SceneCloud
from gcm_pipeline.outputs.scene_glyphs import GripperGlyph
from gcm_pipeline.outputs.scene_shapes import SceneShape, SceneTable
from gcm_pipeline.ranking.metrics import METRIC_COLUMNS
from gcm_pipeline.robot.model import Robot
from gcm_pipeline.robot.model_files import root_link
from gcm_pipeline.sources.grippers import GripperSpec
from gcm_pipeline.table import GraspTable

if TYPE_CHECKING:  # the run module imports this one
    from gcm_pipeline.pipeline.run import RunResult


def scene_shape(section: ObjectConfig | ObstacleConfig) -> SceneShape:
    """The ``object`` or an ``environment.obstacles`` entry as a scene shape."""
    dims = section.dims
    return SceneShape(
        shape=section.shape,
        pose=section.pose.matrix(),
        radius=dims.radius,
        height=dims.height,
        size=dims.size,
        mesh=section.mesh,
        scale=section.scale,
        name=section.name if isinstance(section, ObstacleConfig) else None,
    )


def scene_table(table: TableConfig | None) -> SceneTable | None:
    """The ``environment.table`` section as the scene's support table."""
    if table is None:
        return None
    return SceneTable(height=table.height, size=table.size, center_xy=table.center_xy)


def scene_cloud(cloud: PointCloud) -> SceneCloud:
    """A run's processed point cloud as the scene draws it (a point per voxel)."""
    return SceneCloud(
        cloud.points, cloud.colors, cloud.segments, name=cloud.name, point_size=cloud.voxel_size
    )


def _carried_hand(cfg: Config) -> GripperSpec | None:
    """The registry hand that the robot's model carries (its finger joints locked), or None."""
    locked = set(load_spec(cfg.robot.spec, cfg.robot.tool).locked_joints)
    return next(
        (
            g
            for g in gripper_registry().values()
            if g.finger_joints and set(g.finger_joints) <= locked
        ),
        None,
    )


def run_gripper(cfg: Config, file_gripper: str | None = None) -> GripperSpec | None:
    """The gripper a run's grasps are for, or None when the run does not say.

    In this order: ``candidates.gripper``; ``file_gripper`` (the registry
    gripper a grasp file was mapped by, ``RunResult.grasp_frame``);
    ``robot.tool``; the registry hand the robot's model carries (the Panda's);
    for the antipodal sampler its default hand (``franka_panda``).
    """
    c = cfg.candidates
    if c.gripper is not None:
        return load_gripper(c.gripper)
    if file_gripper is not None and file_gripper in gripper_registry():
        return gripper_registry()[file_gripper]
    if cfg.robot.tool is not None:
        return load_gripper(cfg.robot.tool, "robot.tool")
    hand = _carried_hand(cfg)
    if hand is None and c.source == "antipodal":
        return load_gripper("franka_panda")
    return hand


def gripper_glyph(gripper: GripperSpec | None) -> GripperGlyph:
    """The scene's outline of ``gripper`` (None: the default, the Franka Hand's sizes).

    A parallel-jaw gripper: fingers at ``max_width``, ``finger_length`` and
    ``finger_tip`` along the approach, the palm bar across the fingers
    (``finger_thickness``) and the stem as deep as the palm (``hand.palm_size``
    z). A suction cup: the radius and length of its first cylinder shape
    (else GraspGen's 30 mm cup).
    """
    if gripper is None:
        return GripperGlyph()
    if gripper.kind == "suction":
        shapes = () if gripper.tool is None else gripper.tool.collision
        cyl = next((sh for sh in shapes if sh.shape == "cylinder" and len(sh.size) == 2), None)
        if cyl is None:
            return GripperGlyph(name=gripper.name, kind="suction")
        return GripperGlyph(
            name=gripper.name, kind="suction", cup_radius=cyl.size[0], cup_depth=cyl.size[1]
        )
    return GripperGlyph(
        name=gripper.name,
        opening=gripper.max_width,
        finger_length=gripper.finger_length,
        finger_tip=gripper.finger_tip,
        finger_thickness=gripper.finger_thickness,
        palm_depth=gripper.palm_size[2],
    )


@takes_config
def scene_options(
    cfg: Config, clouds: Sequence[PointCloud] = (), file_gripper: str | None = None
) -> SceneOptions:
    """The scene of a run's config and its processed point clouds.

    Reads ``robot.base_pose``, ``ranking.top_k`` (the animation and the top
    band of reachable grasps), ``continuity.threshold`` (the animation's blend
    limit), ``object``, ``environment`` (table, obstacles) and the run's
    gripper (:func:`run_gripper`; ``file_gripper``: the gripper a grasp file
    was mapped by) for the grasp glyphs.
    """
    env = cfg.environment
    return SceneOptions(
        base_pose=cfg.robot.base_pose.matrix(),
        top_k=cfg.ranking.top_k,
        blend_limit=cfg.continuity.threshold,
        object=None if cfg.object is None else scene_shape(cfg.object),
        table=scene_table(env.table),
        obstacles=tuple(scene_shape(obs) for obs in env.obstacles),
        clouds=tuple(scene_cloud(c) for c in clouds),
        gripper=gripper_glyph(run_gripper(cfg, file_gripper)),
    )


@takes_config
def publish_options(
    cfg: Config, clouds: Sequence[PointCloud] = (), file_gripper: str | None = None
) -> PublishOptions:
    """What a run publishes (section ``publish``) and its scene (:func:`scene_options`)."""
    pub = cfg.publish
    return PublishOptions(
        scene=scene_options(cfg, clouds, file_gripper),
        html=pub.html,
        plots=pub.plots,
        zmq_url=pub.zmq_url,
        connect_timeout_s=pub.connect_timeout_s,
    )


@takes_config
def publish(result: RunResult, cfg: Config, out_dir: str | Path) -> list[Path]:
    """Write ``scene.html`` / PNG plots into ``out_dir`` (section ``publish``).

    Returns:
        The files written.
    """
    counts = {k: v for k, v in result.counts.items() if isinstance(v, int)}
    files = html.publish(
        result.grasps,
        result.manifold,
        result.robot,
        publish_options(cfg, result.clouds, (result.grasp_frame or {}).get("gripper")),
        Path(out_dir),
        counts=counts,
    )
    return list(files)


@takes_config
def open_viewer(
    grasps: GraspTable,
    manifold: Any,
    robot: Robot | None,
    cfg: Config,
    *,
    detach: bool = False,
    clouds: Sequence[PointCloud] = (),
) -> live.Viewer:
    """Publish the scene of ``cfg`` (and its point clouds) to a live meshcat server.

    See :func:`gcm_pipeline.outputs.live.open_viewer` (``publish.zmq_url``).
    """
    options = publish_options(cfg, clouds)
    return live.open_viewer(grasps, manifold, robot, options, detach=detach)


@dataclass(frozen=True)
class ConfigRunExport:
    """A run's config as an export takes it (a :class:`~.outputs.export.RunConfig`).

    Args:
        config: The run's config.
    """

    config: Config

    @property
    def ranking_metric(self) -> str:
        """The run's ranking metric (``ranking.metric``)."""
        return self.config.ranking.metric

    def moveit(self) -> MoveItOptions:
        """The MoveIt export's options of the config and its robot spec.

        Reads ``robot`` (the spec's root and grasp frames and locked joints,
        ``base_pose``, the model's arm joints), ``ranking.metric``, ``approach``
        and ``retreat``.
        """
        cfg = self.config
        spec = load_spec(cfg.robot.spec, cfg.robot.tool)
        robot = load_robot(cfg.robot.spec, cfg.robot.tool)
        retreat = cfg.retreat
        locked = set(spec.locked_joints)
        hand = next(  # a registry hand that the model carries, its fingers locked
            (
                g
                for g in gripper_registry().values()
                if g.finger_joints and set(g.finger_joints) <= locked
            ),
            None,
        )
        return MoveItOptions(
            root_frame=root_link(spec),
            grasp_frame=spec.grasp_frame,
            locked_joints=dict(spec.locked_joints),
            base_pose=cfg.robot.base_pose.matrix(),
            metric=cfg.ranking.metric,
            approach_distance=cfg.approach.distance if cfg.approach is not None else 0.0,
            retreat_direction=None if retreat is None else retreat.direction,
            retreat_frame="world" if retreat is None else retreat.frame,
            retreat_distance=0.0 if retreat is None else retreat.distance,
            finger_joints=() if hand is None else hand.finger_joints,
            hand_frame=None if hand is None else hand.hand_frame,
            joint_names=robot.joint_names,
        )

    def scene(self) -> SceneOptions:
        """The run's scene (:func:`scene_options`; no point clouds)."""
        return scene_options(self.config)


def read_run_config(path: Path) -> ConfigRunExport:
    """A run directory's ``config.yaml`` as an export takes it.

    Raises:
        ConfigError: Not a valid config.
    """
    return ConfigRunExport(load_config(path))


def export_run(
    run_dir: str | os.PathLike[str],
    format: str,
    *,
    top: int | None = None,
    out: str | os.PathLike[str] | None = None,
    trajectory: bool = False,
) -> ExportResult:
    """Export a run directory's grasps: MoveIt grasps (YAML), a ROS 2 bag, Parquet or NPZ.

    See :func:`gcm_pipeline.outputs.export.export_run` (the run's
    ``config.yaml`` is read by :func:`read_run_config`).

    Args:
        run_dir: A run directory written by ``gcm run``.
        format: ``moveit``, ``mcap``, ``parquet`` or ``npz``.
        top: Keep only the ``top`` best-ranked reachable grasps (moveit and
            mcap always export ranked grasps only; default all of them).
        out: The file to write (default: ``RUN_DIR/`` + the format's name in
            :data:`~gcm_pipeline.outputs.export.EXPORT_FORMATS`). Written
            atomically; a symbolic link is kept and the file it names is replaced.
        trajectory: ``moveit``: each grasp with the arm's joint trajectory.

    Returns:
        The file and the number of grasps written.

    Raises:
        InputError: Not a run directory, unknown format, ``top < 1``, ``out``
            naming one of the run's own files, no usable ``configurations.npz``
            (mcap, trajectory), rosbags missing (mcap), or no reachable grasp to
            export (after an empty, valid file is written).
        ConfigError: The run's ``config.yaml`` is not a valid config.
        OutputError: The file cannot be written, or ``out`` is a directory, a
            device or a pipe.
    """
    return export.export_run(
        run_dir, format, read_config=read_run_config, top=top, out=out, trajectory=trajectory
    )


def top_grasps(grasps: GraspTable, n: int, metric: str = "yoshikawa") -> list[dict[str, Any]]:
    """The ``n`` best-ranked grasps as plain dicts (rank, pose, metrics, q).

    Each has ``rank, row, origin, x, y, z, qw, qx, qy, qz`` (``qw >= 0``),
    ``manipulability``, the ranking metric's column when it is another one,
    and ``q``. Rows without a ``rank`` column, or unranked (rank 0), are left out.
    """
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
