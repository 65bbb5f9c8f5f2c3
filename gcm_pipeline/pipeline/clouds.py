"""``environment.point_clouds``: the config's scene clouds read, and as collision shapes.

Each cloud is read once per process for the same config and files
(:func:`scene_clouds` keeps the last answer: the reachability stage, the
adaptive refinement and the run directory all ask for it).
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any

import numpy as np

from gcm_pipeline.config.reach_sections import EnvironmentConfig, PointCloudConfig
from gcm_pipeline.config.sections import ObjectConfig, Pose
from gcm_pipeline.errors import ConfigError
from gcm_pipeline.geometry.clouds import NO_SEGMENT, PointCloud
from gcm_pipeline.robot import collision
from gcm_pipeline.robot.collision.clouds import MAX_TILES, cloud_shapes, within_distance
from gcm_pipeline.robot.collision.world import WorldShape
from gcm_pipeline.sources.clouds import CloudOptions, read_cloud
from gcm_pipeline.table import GraspTable

log = logging.getLogger(__name__)

__all__ = [
    "cloud_key",
    "cloud_options",
    "cloud_summary",
    "cloud_world",
    "grasp_segments",
    "scene_clouds",
    "segment_groups",
    "table_merge",
    "table_subset",
]

#: The last clouds read: (key, clouds).
_LAST: list[tuple[Any, list[PointCloud]]] = []


def cloud_options(
    i: int,
    pc: PointCloudConfig,
    object_cfg: ObjectConfig | None,
    camera_pose: Pose | None,
) -> CloudOptions:
    """The reader's options of ``environment.point_clouds[i]``.

    ``camera_pose`` is ``candidates.camera_pose``, used when a camera-frame
    cloud gives none.

    Raises:
        ConfigError: A camera-frame cloud without a camera pose;
            ``exclude_object_distance`` without an ``object``.
    """
    where = f"environment.point_clouds[{i}]"
    camera = None
    if pc.frame == "camera":
        pose = pc.camera_pose if pc.camera_pose is not None else camera_pose
        if pose is None:
            raise ConfigError(
                f"{where}: frame 'camera' needs camera_pose (the camera's optical frame in the "
                "world, OpenCV: x right, y down, z forward), or candidates.camera_pose; "
                "or frame: world"
            )
        camera = pose.matrix()
    exclude = None
    if pc.exclude_object_distance is not None:
        if object_cfg is None:
            raise ConfigError(f"{where}.exclude_object_distance needs an 'object' section")
        o, dist = object_cfg, pc.exclude_object_distance
        shape = collision.object_shape(
            o.shape, o.dims, o.pose.matrix(), np.eye(4), mesh=o.mesh, scale=o.scale
        )

        def exclude(points: np.ndarray) -> np.ndarray:
            return within_distance(shape, points, dist)

    crop = None
    if pc.crop_min is not None or pc.crop_max is not None:
        lo = np.full(3, -np.inf) if pc.crop_min is None else np.asarray(pc.crop_min)
        hi = np.full(3, np.inf) if pc.crop_max is None else np.asarray(pc.crop_max)
        crop = (lo, hi)
    return CloudOptions(
        path=Path(pc.path),
        voxel_size=pc.voxel_size,
        camera_pose=camera,
        intrinsics=None if pc.intrinsics is None else np.asarray(pc.intrinsics, dtype=float),
        depth_scale=pc.depth_scale,
        segmap=None if pc.segmap is None else Path(pc.segmap),
        max_depth=pc.max_depth,
        crop=crop,
        exclude_segments=tuple(pc.exclude_segments),
        exclude=exclude,
        name=pc.name or f"cloud_{i}",
        where=where,
    )


def _stamp(path: Path | None) -> Any:
    if path is None:
        return None
    try:
        st = Path(path).stat()
    except OSError:
        return None
    return (str(path), st.st_mtime_ns, st.st_size)


def scene_clouds(
    environment: EnvironmentConfig | None,
    object_cfg: ObjectConfig | None = None,
    camera_pose: Pose | None = None,
) -> list[PointCloud]:
    """The processed clouds of ``environment.point_clouds`` (world frame, voxelised).

    Raises:
        ConfigError: See :func:`cloud_options`.
        InputError: A cloud file that cannot be read, or with no point left.
    """
    if environment is None or not environment.point_clouds:
        return []
    key = (
        environment.point_clouds,
        object_cfg,
        camera_pose,
        tuple((_stamp(pc.path), _stamp(pc.segmap)) for pc in environment.point_clouds),
    )
    if _LAST and _LAST[0][0] == key:
        return _LAST[0][1]
    clouds = []
    for i, pc in enumerate(environment.point_clouds):
        cloud = read_cloud(cloud_options(i, pc, object_cfg, camera_pose))
        c = cloud.counts
        log.info(
            "%s: %s: %d points read, %d non-finite dropped, %d excluded, %d voxels of %g m",
            *(f"environment.point_clouds[{i}]", pc.path, c["read"], c["non_finite"]),
            c["excluded_segments"] + c["excluded_object"],
            *(c["voxels"], cloud.voxel_size),
        )
        if pc.exclude_segments and not c["excluded_segments"]:
            ids = [] if cloud.segments is None else np.unique(cloud.segments).tolist()
            log.warning(
                "environment.point_clouds[%d].exclude_segments %s matched no point of %s "
                "(its segment ids: %s)",
                *(i, list(pc.exclude_segments), pc.path, ids[:20]),
            )
        clouds.append(cloud)
    _LAST[:] = [(key, clouds)]
    return clouds


def cloud_world(
    environment: EnvironmentConfig | None,
    object_cfg: ObjectConfig | None,
    base_inv: np.ndarray,
    camera_pose: Pose | None = None,
    grasp_segment: int | None = None,
) -> list[WorldShape]:
    """The clouds' octree tiles (kind ``environment``) in the robot's base frame.

    At most :data:`~gcm_pipeline.robot.collision.clouds.MAX_TILES` tiles in all
    (shared by the clouds, at least one each).

    ``grasp_segment``: the segment of the grasps checked, left out of the clouds
    with ``exclude_grasp_segment`` (a voxel another segment shares stays).
    """
    shapes: list[WorldShape] = []
    if environment is None:
        return shapes
    clouds = scene_clouds(environment, object_cfg, camera_pose)
    # one budget of tiles for all clouds: each tile costs the checker an obstacle's memory
    per_cloud = max(1, MAX_TILES // max(1, len(clouds)))
    for pc, cloud in zip(environment.point_clouds, clouds, strict=True):
        drop = () if grasp_segment is None or not pc.exclude_grasp_segment else (grasp_segment,)
        points = cloud.occupied(drop)
        if not len(points):
            continue  # the grasps' own segment is the whole cloud
        shapes += cloud_shapes(points, cloud.voxel_size, base_inv, cloud.name, per_cloud)
    return shapes


def cloud_key(environment: EnvironmentConfig, shape: str) -> str | None:
    """The config location of the cloud a world shape (``<name>_<tile>``) is a tile of, or None."""
    for i, pc in enumerate(environment.point_clouds):
        name = pc.name or f"cloud_{i}"
        head, _, tile = shape.rpartition("_")
        if head == name and tile.isdigit():
            return f"environment.point_clouds[{i}] ({name})"
    return None


def grasp_segments(grasps: GraspTable) -> np.ndarray:
    """Each row's segment (N,) int64: its ``segment``, or its vertices' when they share one.

    -1 where there is none (no column, or vertices of several segments).
    """
    n = len(grasps)
    if "segment" not in grasps:
        return np.full(n, NO_SEGMENT, np.int64)
    seg = np.asarray(grasps["segment"], dtype=np.int64).copy()
    if "vertices" in grasps:
        vert = np.asarray(grasps["vertices"], dtype=np.int64)
        ok = (vert >= 0) & (vert < n)
        own = np.where(ok, seg[np.clip(vert, 0, max(n - 1, 0))], NO_SEGMENT)
        first = own[:, 0]
        agree = np.all(ok, axis=1) & np.all(own == first[:, None], axis=1)
        fill = (seg == NO_SEGMENT) & agree
        seg[fill] = first[fill]
    return seg


def segment_groups(
    grasps: GraspTable, environment: EnvironmentConfig | None
) -> list[tuple[int | None, np.ndarray]] | None:
    """Rows grouped by their segment when a cloud excludes each grasp's own, else None.

    Returns ``[(segment or None, rows), ...]`` (None: rows without a segment,
    checked against the whole clouds).
    """
    if environment is None or "segment" not in grasps:
        return None
    if not any(pc.exclude_grasp_segment for pc in environment.point_clouds):
        return None
    seg = grasp_segments(grasps)
    groups: list[tuple[int | None, np.ndarray]] = []
    for s in np.unique(seg).tolist():
        groups.append((None if s == NO_SEGMENT else int(s), np.flatnonzero(seg == s)))
    return groups


def table_subset(grasps: GraspTable, rows: np.ndarray) -> GraspTable:
    """Rows of a table, its ``vertices`` row ids renumbered (-1: a row left out)."""
    sub = grasps.take(rows)
    if "vertices" not in sub:
        return sub
    index = np.full(len(grasps) + 1, -1, np.int64)
    index[rows] = np.arange(len(rows))
    vert = np.asarray(sub["vertices"], dtype=np.int64)
    inside = (vert >= 0) & (vert < len(grasps))
    return sub.with_columns(vertices=np.where(inside, index[np.where(inside, vert, -1)], -1))


def table_merge(grasps: GraspTable, parts: list[tuple[np.ndarray, GraspTable]]) -> GraspTable:
    """``grasps`` with the columns the parts (rows, table) added, each row from its part."""
    n = len(grasps)
    new: dict[str, np.ndarray] = {}
    # every column but the renumbered vertices (the input's come back as they went)
    names = [c for c in parts[0][1].columns if c != "vertices"]
    for name in names:
        arrays = [np.asarray(t[name]) for _, t in parts]
        out = np.zeros((n, *arrays[0].shape[1:]), dtype=np.result_type(*arrays))
        for (rows, _), arr in zip(parts, arrays, strict=True):
            out[rows] = arr
        new[name] = out
    return grasps.with_columns(**new)


def cloud_summary(clouds: list[PointCloud]) -> list[dict[str, Any]]:
    """What ``summary.json`` records of each cloud (``point_clouds``)."""
    return [
        {"name": c.name, "path": c.source, "voxel_size": c.voxel_size, "counts": dict(c.counts)}
        for c in clouds
    ]
