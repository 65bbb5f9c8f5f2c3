"""Grasps in and out: synthesisers' file formats, the gripper registry, exporters.

:func:`load_candidates` is the candidate stage's entry for the sources this
package handles: ``candidates.source: file`` with ``format: graspgen |
contact_graspnet | graspnet`` (or ``acronym`` with a ``gripper``), and
``candidates.source: antipodal`` (the sampler,
:mod:`gcm_pipeline.stages.antipodal`). It returns the grasp-frame poses in the
world and the per-candidate columns to carry through the grasp table.

Frames, in order (``T`` a pose as the file stores it):

1. gripper: ``T_tool = T @ gripper.to_tool(convention)`` (the named
   ``candidates.gripper``, default ``franka_panda``), or
   ``T @ candidates.grasp_to_tool`` when that is given instead;
2. into the world: ``camera_pose @ T_tool`` with ``candidates.camera_pose``
   (required for ``contact_graspnet``, whose poses are in the camera's
   OpenCV optical frame: x right, y down, z forward), else
   ``object.pose @ T_tool`` for ``frame: object``, else ``T_tool``.
"""

from __future__ import annotations

import logging
from typing import TYPE_CHECKING

import numpy as np

from gcm_pipeline.errors import InputError
from gcm_pipeline.formats.grippers import (
    CONVENTIONS,
    GRIPPERS,
    GripperSpec,
    get_gripper,
    gripper_names,
)
from gcm_pipeline.formats.importers import (
    IMPORT_FORMATS,
    READERS,
    ImportedGrasps,
    read_contact_graspnet,
    read_graspgen,
    read_graspnet,
)

if TYPE_CHECKING:
    from gcm_pipeline.config import Config

__all__ = [
    "CONVENTIONS",
    "GRIPPERS",
    "IMPORT_FORMATS",
    "GripperSpec",
    "ImportedGrasps",
    "get_gripper",
    "gripper_names",
    "handles",
    "load_candidates",
    "read_contact_graspnet",
    "read_graspgen",
    "read_graspnet",
]

log = logging.getLogger(__name__)

DEFAULT_GRIPPER = "franka_panda"


def handles(cfg: Config) -> bool:
    """Whether :func:`load_candidates` (not the built-in readers) produces ``cfg``'s candidates."""
    c = cfg.candidates
    if c.source == "antipodal":
        return True
    return c.source == "file" and (
        c.format in IMPORT_FORMATS or (c.format == "acronym" and c.gripper is not None)
    )


def load_candidates(cfg: Config) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    """World poses (N, 4, 4) of the robot's grasp frame and per-candidate columns.

    Args:
        cfg: A config for which :func:`handles` is true.

    Returns:
        ``(poses, columns)``: columns (N,) such as ``score``, ``width``,
        ``source_id``, ``segment``, ``object_id`` (see
        :data:`gcm_pipeline.table.CANDIDATE_COLUMNS`).

    Raises:
        InputError: An unreadable file or one of the wrong format.
        ConfigError: An unknown gripper.
    """
    c = cfg.candidates
    if c.source == "antipodal":
        from gcm_pipeline.stages.antipodal import sample_antipodal_config

        return sample_antipodal_config(cfg)
    assert c.path is not None and c.format is not None
    grasps = _read(c.format, c.path, c.success_only, c.limit, c.max_count)
    poses = grasps.poses
    if c.grasp_to_tool is not None:
        poses = poses @ c.grasp_to_tool.matrix()
    else:
        name = c.gripper or DEFAULT_GRIPPER
        if grasps.gripper is not None and grasps.gripper != name:
            log.warning(
                "%s: grasps made for gripper %r are mapped onto %r", c.path, grasps.gripper, name
            )
        poses = poses @ get_gripper(name).to_tool(grasps.convention, grasps.depth)
    if c.camera_pose is not None:
        poses = c.camera_pose.matrix() @ poses
    elif c.frame == "object":
        assert cfg.object is not None
        poses = cfg.object.pose.matrix() @ poses
    return poses, grasps.columns


def _read(
    fmt: str, path: object, success_only: bool, limit: int | None, max_count: int
) -> ImportedGrasps:
    if fmt == "acronym":  # the built-in reader filters; source_id and success as without a gripper
        from gcm_pipeline.stages.candidates import read_grasp_file

        poses, columns = read_grasp_file(
            path,  # type: ignore[arg-type]
            format="acronym",
            success_only=success_only,
            limit=limit,
            max_count=max_count,
        )
        return ImportedGrasps(poses, "base", columns)
    grasps = READERS[fmt](path, max_count=max_count)  # type: ignore[arg-type]
    if success_only:
        if grasps.success is None:
            raise InputError(
                f"{path}: candidates.success_only needs success labels, but this {fmt} "
                "file has none (graspgen: grasps.object_in_gripper)"
            )
        grasps = grasps.take(np.flatnonzero(grasps.success))
    if limit is not None:
        grasps = grasps.take(np.arange(min(limit, len(grasps.poses))))
    return grasps
