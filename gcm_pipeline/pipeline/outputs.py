"""The ``publish`` step: a config onto the scene's options; the best grasps as plain dicts."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from gcm_pipeline.config.reach_sections import ObstacleConfig, TableConfig
from gcm_pipeline.config.run import Config, takes_config
from gcm_pipeline.config.sections import ObjectConfig
from gcm_pipeline.geometry.dualquat import dq_to_pos_quat
from gcm_pipeline.outputs import html, live
from gcm_pipeline.outputs.scene import PublishOptions, SceneOptions
from gcm_pipeline.outputs.scene_shapes import SceneShape, SceneTable
from gcm_pipeline.ranking.metrics import METRIC_COLUMNS
from gcm_pipeline.robot.model import Robot
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


@takes_config
def scene_options(cfg: Config) -> SceneOptions:
    """The scene of a run's config.

    Reads ``robot.base_pose``, ``ranking.top_k``, ``continuity.threshold`` (the
    animation's blend limit), ``object`` and ``environment`` (table, obstacles).
    """
    env = cfg.environment
    return SceneOptions(
        base_pose=cfg.robot.base_pose.matrix(),
        top_k=cfg.ranking.top_k,
        blend_limit=cfg.continuity.threshold,
        object=None if cfg.object is None else scene_shape(cfg.object),
        table=scene_table(env.table),
        obstacles=tuple(scene_shape(obs) for obs in env.obstacles),
    )


@takes_config
def publish_options(cfg: Config) -> PublishOptions:
    """What a run publishes (section ``publish``) and its scene (:func:`scene_options`)."""
    pub = cfg.publish
    return PublishOptions(
        scene=scene_options(cfg),
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
        publish_options(cfg),
        Path(out_dir),
        counts=counts,
    )
    return list(files)


@takes_config
def open_viewer(
    grasps: GraspTable, manifold: Any, robot: Robot | None, cfg: Config, *, detach: bool = False
) -> live.Viewer:
    """Publish the scene of ``cfg`` to a live meshcat server (``publish.zmq_url``).

    See :func:`gcm_pipeline.outputs.live.open_viewer`.
    """
    return live.open_viewer(grasps, manifold, robot, publish_options(cfg), detach=detach)


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
