"""The object a grasp file names, placed on the table: a config's ``object`` filled in."""

from __future__ import annotations

import logging
import math
from pathlib import Path

from scipy.spatial.transform import Rotation

from gcm_pipeline.config.run import Config, takes_config
from gcm_pipeline.config.sections import ObjectConfig, PlacementConfig, Pose
from gcm_pipeline.sources.file_object import (
    MESH_KEYS,
    find_mesh,
    load_scaled,
    named_object,
    stable_placement,
)
from gcm_pipeline.sources.files import file_format

log = logging.getLogger(__name__)


@takes_config
def place_file_object(cfg: Config) -> Config:
    """``cfg`` with the object its grasp file names, stood on the table; else ``cfg`` itself.

    Applies to ``source: file`` in a format that names its mesh (``acronym``,
    ``graspgen``) when the file names one, the config has no ``object``
    section (an explicit object wins) and no ``candidates.frame``. The mesh
    is found under ``candidates.mesh_root``
    (:func:`~gcm_pipeline.sources.file_object.find_mesh`), scaled by the
    file's scale and placed by ``candidates.placement``; the grasps then
    follow it (``frame: object``).

    Raises:
        InputError: The mesh is not found (names every path tried), cannot be
            read, the file's scale is not a positive finite number, or the
            stable pose index is out of range.
    """
    c = cfg.candidates
    if cfg.object is not None and (c.mesh_root is not None or c.placement != PlacementConfig()):
        log.warning(
            "candidates.%s: not used, the 'object' section gives the object",
            "mesh_root" if c.mesh_root is not None else "placement",
        )
    if c.source != "file" or cfg.object is not None or c.frame is not None:
        return cfg
    assert c.path is not None
    fmt = file_format(c.path, c.format)
    path = Path(c.path)
    name, scale = named_object(path, fmt, c.max_count)
    if name is None or fmt is None:
        return cfg
    mesh_path = find_mesh(path, name, fmt, c.mesh_root)
    what = f"{path}: {MESH_KEYS[fmt]} -> {mesh_path}"
    mesh = load_scaled(mesh_path, scale, what)
    table = cfg.environment.table
    p = c.placement
    placed = stable_placement(
        mesh,
        p.xy,
        math.radians(p.yaw_deg),
        0.0 if table is None else table.height,
        None if p.stable_pose == "upright" else p.stable_pose,
        what,
    )
    m = placed.pose
    rpy = Rotation.from_matrix(m[:3, :3]).as_euler("xyz")  # R = Rz(yaw) Ry(pitch) Rx(roll)
    pose = Pose(xyz=tuple(float(v) for v in m[:3, 3]), rpy=tuple(float(v) for v in rpy))
    obj = ObjectConfig(shape="mesh", mesh=mesh_path, scale=scale, pose=pose)
    log.info(
        "object: %s (scale %g) from %s, stable pose %d of %d (probability %.2f) at xy %s, "
        "yaw %g deg",
        mesh_path,
        scale,
        path.name,
        placed.index,
        placed.count,
        placed.probability,
        list(p.xy),
        p.yaw_deg,
    )
    return cfg.model_copy(
        update={"object": obj, "candidates": c.model_copy(update={"frame": "object"})}
    )
