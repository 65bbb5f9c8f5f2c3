"""Grasps in and out: synthesisers' file formats, the gripper registry, exporters.

:func:`load_candidates` is the candidate stage's entry for the sources this
package handles: ``candidates.source: file`` with ``format: acronym | graspgen |
contact_graspnet | graspnet``, and
``candidates.source: antipodal`` (the sampler,
:mod:`gcm_pipeline.stages.antipodal`). It returns the grasp-frame poses in the
world and the per-candidate columns to carry through the grasp table.

Frames, in order (``T`` a pose as the file stores it):

1. gripper: ``T_tool = T @ gripper.to_tool(convention)``, or
   ``T @ candidates.grasp_to_tool`` when that is given instead. The gripper
   is, in this order: ``candidates.gripper``; the gripper the file names
   (ACRONYM's ``gripper/type``, GraspGen's ``gripper``), which the registry
   must know; the format's dataset gripper
   (:data:`~gcm_pipeline.formats.grippers.DATASET_GRIPPERS`: ``franka_panda``
   for ACRONYM, Contact-GraspNet and GraspNet). A file with none of these (a
   GraspGen file that names no gripper) or naming an unknown gripper is
   refused with the choices. The choice is logged and returned
   (:class:`GripperChoice`, ``summary.json``'s ``grasp_frame``);
2. into the world: ``camera_pose @ T_tool`` with ``candidates.camera_pose``
   (required for ``contact_graspnet``, whose poses are in the camera's
   OpenCV optical frame: x right, y down, z forward), else
   ``object.pose @ T_tool`` for ``frame: object``, else ``T_tool``.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from gcm_pipeline.errors import ConfigError, InputError
from gcm_pipeline.formats.grippers import (
    CONVENTIONS,
    DATASET_GRIPPERS,
    GRIPPERS,
    GripperSpec,
    find_gripper,
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
    "DATASET_GRIPPERS",
    "GRIPPERS",
    "GRIPPER_FORMATS",
    "IMPORT_FORMATS",
    "GripperChoice",
    "GripperSpec",
    "ImportedGrasps",
    "choose_gripper",
    "find_gripper",
    "get_gripper",
    "gripper_names",
    "handles",
    "load_candidates",
    "load_candidates_choice",
    "read_contact_graspnet",
    "read_graspgen",
    "read_graspnet",
]

log = logging.getLogger(__name__)

#: Formats whose poses are a gripper's frame (and their frame convention).
GRIPPER_FORMATS: dict[str, str] = {"acronym": "base", **IMPORT_FORMATS}

#: The format a grasp file's suffix implies when ``candidates.format`` is not given.
_SUFFIX_FORMATS = {".h5": "acronym", ".hdf5": "acronym", ".json": "graspgen"}
_SUFFIX_FORMATS |= {".yaml": "graspgen", ".yml": "graspgen"}


def _file_format(cfg: Config) -> str | None:
    c = cfg.candidates
    if c.format is not None or c.path is None:
        return c.format
    return _SUFFIX_FORMATS.get(Path(c.path).suffix.lower())


def handles(cfg: Config) -> bool:
    """Whether :func:`load_candidates` (not the built-in readers) produces ``cfg``'s candidates."""
    c = cfg.candidates
    if c.source == "antipodal":
        return True
    return c.source == "file" and _file_format(cfg) in GRIPPER_FORMATS


@dataclass(frozen=True)
class GripperChoice:
    """How a grasp file's gripper frame is mapped onto the robot's grasp frame.

    Attributes:
        format: The file's format.
        gripper: The registry gripper used, or None (``grasp_to_tool``).
        chosen_by: ``config`` (``candidates.gripper``), ``file`` (the gripper
            the file names), ``dataset`` (the format's dataset gripper,
            :data:`DATASET_GRIPPERS`) or ``grasp_to_tool``.
        file_gripper: The gripper as the file names it, if it does.
    """

    format: str
    gripper: str | None
    chosen_by: str
    file_gripper: str | None = None

    def describe(self) -> str:
        """One line for the run's output."""
        named = f", the file names {self.file_gripper!r}" if self.file_gripper else ""
        if self.gripper is None:
            return f"{self.format} poses mapped by candidates.grasp_to_tool{named}"
        why = {
            "config": "candidates.gripper",
            "file": "named by the file",
            "dataset": f"the {self.format} dataset's gripper",
        }[self.chosen_by]
        return f"{self.gripper} ({why}{named if self.chosen_by != 'file' else ''})"

    def as_dict(self) -> dict[str, Any]:
        """``summary.json``'s ``grasp_frame``."""
        return {
            "format": self.format,
            "gripper": self.gripper,
            "chosen_by": self.chosen_by,
            "file_gripper": self.file_gripper,
        }


def choose_gripper(
    path: object, fmt: str, configured: str | None, mapped: bool, file_gripper: str | None
) -> GripperChoice:
    """The gripper whose frame the file's poses are in (see the module docstring).

    Args:
        path: The file (for messages).
        fmt: Its format (one of :data:`GRIPPER_FORMATS`).
        configured: ``candidates.gripper``.
        mapped: Whether ``candidates.grasp_to_tool`` is given.
        file_gripper: The gripper the file names, if any.

    Raises:
        InputError: The file names a gripper the registry does not know, or
            names none and its format has no dataset gripper (the message
            lists the known grippers and ``grasp_to_tool``; attributes ``key``,
            ``value``: the file's gripper, ``choices``).
    """
    if mapped:
        return GripperChoice(fmt, None, "grasp_to_tool", file_gripper)
    known = ", ".join(gripper_names())
    if configured is not None:
        spec = get_gripper(configured)
        if file_gripper is not None and find_gripper(file_gripper) is not spec:
            log.warning(
                "%s: grasps made for gripper %r are mapped onto %r (candidates.gripper)",
                path,
                file_gripper,
                spec.name,
            )
        return GripperChoice(fmt, spec.name, "config", file_gripper)
    if file_gripper is not None:
        found = find_gripper(file_gripper)
        if found is None:
            raise _refused(
                f"{path}: its grasps are for gripper {file_gripper!r}, which the gripper "
                f"registry does not know (known: {known}); give candidates.grasp_to_tool "
                "(its gripper frame -> the robot's grasp frame), or candidates.gripper to "
                "map it as a known one",
                path,
                file_gripper,
            )
        return GripperChoice(fmt, found.name, "file", file_gripper)
    if fmt in DATASET_GRIPPERS:
        return GripperChoice(fmt, DATASET_GRIPPERS[fmt], "dataset")
    raise _refused(
        f"{path}: this {fmt} file does not name its gripper, and {fmt} grasps are made for "
        "several grippers whose frames differ; set candidates.gripper (one of: "
        f"{known}) or candidates.grasp_to_tool",
        path,
        None,
    )


def _refused(message: str, path: object, value: str | None) -> InputError:
    err = InputError(message)
    err.path, err.key, err.value = path, "candidates.gripper", value  # type: ignore[attr-defined]
    err.choices = (*gripper_names(), "grasp_to_tool")  # type: ignore[attr-defined]
    return err


def load_candidates(cfg: Config) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    """World poses (N, 4, 4) of the robot's grasp frame and per-candidate columns.

    Args:
        cfg: A config for which :func:`handles` is true.

    Returns:
        ``(poses, columns)``: columns (N,) such as ``score``, ``width``,
        ``source_id``, ``segment``, ``object_id`` (see
        :data:`gcm_pipeline.table.CANDIDATE_COLUMNS`).

    Raises:
        InputError: An unreadable file, one of the wrong format, or one whose
            gripper is unknown (:func:`choose_gripper`).
        ConfigError: An unknown gripper.
    """
    poses, columns, _ = load_candidates_choice(cfg)
    return poses, columns


def load_candidates_choice(
    cfg: Config,
) -> tuple[np.ndarray, dict[str, np.ndarray], GripperChoice | None]:
    """:func:`load_candidates`, plus how a file's gripper frame was mapped (None: sampled)."""
    c = cfg.candidates
    if c.source == "antipodal":
        from gcm_pipeline.stages.antipodal import sample_antipodal_config

        return (*sample_antipodal_config(cfg), None)
    fmt = _file_format(cfg)
    assert c.path is not None and fmt is not None
    grasps = _read(fmt, c.path, c.success_only, c.limit, c.max_count)
    choice = choose_gripper(c.path, fmt, c.gripper, c.grasp_to_tool is not None, grasps.gripper)
    log.info("candidates: %s: gripper frame of %s", c.path, choice.describe())
    poses = grasps.poses
    if c.grasp_to_tool is not None:
        poses = poses @ c.grasp_to_tool.matrix()
    else:
        assert choice.gripper is not None
        poses = poses @ get_gripper(choice.gripper).to_tool(grasps.convention, grasps.depth)
    if c.camera_pose is not None:
        poses = c.camera_pose.matrix() @ poses
    elif c.frame == "object":
        if cfg.object is None:
            raise ConfigError("candidates.frame 'object' needs an 'object' section")
        poses = cfg.object.pose.matrix() @ poses
    return poses, grasps.columns, choice


def _read(
    fmt: str, path: object, success_only: bool, limit: int | None, max_count: int
) -> ImportedGrasps:
    if fmt == "acronym":  # the built-in reader filters; source_id and success as without a gripper
        from gcm_pipeline.stages.candidates import read_grasp_file_gripper

        poses, columns, gripper = read_grasp_file_gripper(
            path,  # type: ignore[arg-type]
            format="acronym",
            success_only=success_only,
            limit=limit,
            max_count=max_count,
        )
        return ImportedGrasps(poses, "base", columns, gripper=gripper)
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
