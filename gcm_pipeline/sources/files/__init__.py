"""Grasp files: one reader per format, and the map of a file's poses onto the robot's grasp frame.

========================= ============================================================
format                    module (layout read)
========================= ============================================================
``npy``                   :mod:`~.npy`: one array (N, 4, 4) of grasp-frame poses
``npz``                   :mod:`~.npz`: ``transforms`` (N, 4, 4), ``success``, columns
``csv``                   :mod:`~.csv`: ``x,y,z,qw,qx,qy,qz`` (+ ``success``, columns)
``acronym``               :mod:`~.acronym`: ACRONYM's HDF5 files (Franka hand base)
``graspgen``              :mod:`~.graspgen`: GraspGen's JSON/YAML and ``isaac_grasp``
``contact_graspnet``      :mod:`~.contact_graspnet`: ``predictions_*.npz``
``graspnet``              :mod:`~.graspnet`: GraspNet-1Billion / AnyGrasp rows
========================= ============================================================

:func:`read_grasps` reads any of them as the file stores them
(:class:`ImportedGrasps`); :func:`to_grasp_frame` maps the poses onto the
robot's grasp frame: ``npy``/``npz``/``csv`` poses are that frame already
(``T_tool = T @ grasp_to_tool`` when a map is given); the other formats store
a synthesiser's gripper frame, mapped by ``grasp_to_tool`` or else by the
gripper registry (``T_tool = T @ gripper.to_tool(convention)``,
:func:`~gcm_pipeline.sources.grippers.choose_gripper` picks the gripper).
A file whose first bytes show another format is refused naming it
(:mod:`~.sniff`).

Imported poses (``source: file``) are read as stored (:func:`load_grasp_file`),
then mapped onto the robot's grasp frame by ``grasp_to_tool`` on the right,
``T_tool = T_grasp @ grasp_to_tool``, and into the world by the object pose when
``frame: object``: ``T_world = T_object @ T_tool``. (``format: acronym`` and the
synthesisers' formats map their gripper frame by the gripper registry instead,
see :func:`to_grasp_frame`.) For poses in ACRONYM's Franka gripper frame
(origin at the hand base, z = approach, fingers closing along x: its finger
control points are at x = +-0.041 m) written as ``npy``/``npz``/``csv``, and the
Panda's ``panda_hand_tcp`` (0.1034 m further along z, fingers closing along y) use
``grasp_to_tool: {xyz: [0, 0, 0.1034], rpy_deg: [0, 0, -90]}``: the tool's y
axis is then the gripper's +x axis, its origin the midpoint of the fingertips,
its z the same approach (``tests/sources/test_candidates.py`` checks this geometry).
``rpy_deg: [0, 0, 90]`` is the same grasp turned by 180 deg about the
approach: the symmetric hand cannot tell the two apart, but the arm reaches
them with joint 7 differing by pi, so the choice can change reachability.
"""

from __future__ import annotations

import logging
from collections.abc import Mapping
from pathlib import Path

import numpy as np

from gcm_pipeline.bounds import DEFAULT_MAX_CANDIDATES
from gcm_pipeline.errors import InputError, clip
from gcm_pipeline.sources.files.acronym import ACRONYM_INSTALL_HINT, read_acronym
from gcm_pipeline.sources.files.common import ImportedGrasps, check_positions, check_rigid
from gcm_pipeline.sources.files.contact_graspnet import read_contact_graspnet
from gcm_pipeline.sources.files.csv import read_csv
from gcm_pipeline.sources.files.graspgen import read_graspgen
from gcm_pipeline.sources.files.graspnet import read_graspnet
from gcm_pipeline.sources.files.npy import read_npy
from gcm_pipeline.sources.files.npz import read_npz
from gcm_pipeline.sources.files.select import Selection, select_grasps
from gcm_pipeline.sources.files.sniff import check_format, sniff
from gcm_pipeline.sources.grippers import GripperChoice, GripperSpec, choose_gripper

__all__ = [
    "ACRONYM_INSTALL_HINT",
    "GRIPPER_FORMATS",
    "IMPORT_FORMATS",
    "READERS",
    "ImportedGrasps",
    "Selection",
    "file_format",
    "load_grasp_file",
    "read_contact_graspnet",
    "read_grasp_file",
    "read_grasp_file_gripper",
    "read_graspgen",
    "read_graspnet",
    "read_grasps",
    "to_grasp_frame",
]

log = logging.getLogger(__name__)

#: Synthesisers' formats read into :class:`ImportedGrasps`, with the gripper-frame
#: convention of their poses.
IMPORT_FORMATS: dict[str, str] = {
    "graspgen": "base",
    "contact_graspnet": "base",
    "graspnet": "center",
}

#: Their readers.
READERS = {
    "graspgen": read_graspgen,
    "contact_graspnet": read_contact_graspnet,
    "graspnet": read_graspnet,
}

#: Formats whose poses are a gripper's frame (and their frame convention).
GRIPPER_FORMATS: dict[str, str] = {"acronym": "base", **IMPORT_FORMATS}

#: The gripper format a grasp file's suffix implies when no format is given.
_SUFFIX_FORMATS = {".h5": "acronym", ".hdf5": "acronym", ".json": "graspgen"}
_SUFFIX_FORMATS |= {".yaml": "graspgen", ".yml": "graspgen"}


def file_format(path: str | Path, format: str | None) -> str | None:
    """``format``, else the gripper format ``path``'s suffix implies, else None.

    None: one of ``npy``, ``npz``, ``csv``, told by :func:`read_grasp_file`
    from the suffix.
    """
    if format is not None:
        return format
    return _SUFFIX_FORMATS.get(Path(path).suffix.lower())


def read_grasps(
    path: str | Path,
    fmt: str | None,
    *,
    success_only: bool | None = None,
    min_score: float | None = None,
    limit: int | None = None,
    max_count: int = DEFAULT_MAX_CANDIDATES,
) -> ImportedGrasps:
    """The grasps of a file in any format, as stored, filtered (:mod:`~.select`).

    Args:
        path: The grasp file.
        fmt: Its format (:func:`file_format`; None: from the suffix).
        success_only: Keep only successful grasps (True needs success labels;
            None: when the file has them).
        min_score: Keep only grasps whose ``score`` is at least this (needs a score).
        limit: Keep at most this many (after the filters above): the best by
            ``score`` when the file has one (ties: file order), else the first.
        max_count: Most grasps the file may hold (``candidates.max_count``).

    Returns:
        The grasps; ``convention`` is ``tool`` for ``npy``/``npz``/``csv``
        (poses of the robot's grasp frame) and the format's gripper-frame
        convention otherwise; ``selection`` says what was kept.

    Raises:
        InputError: See :func:`read_grasp_file` and the format's reader.
    """
    if fmt in READERS:
        assert fmt is not None
        grasps = READERS[fmt](path, max_count=max_count)
    else:
        poses, columns, gripper = _read_builtin(path, fmt, max_count)
        conv = "base" if fmt == "acronym" else "tool"
        grasps = ImportedGrasps(poses, conv, columns, columns.get("success"), gripper=gripper)
    if "source_id" not in grasps.columns:  # an empty file
        grasps.columns["source_id"] = np.arange(len(grasps.poses), dtype=np.int64)
    keep, selection = select_grasps(
        path,
        fmt,
        grasps.columns,
        grasps.success,
        success_only=success_only,
        min_score=min_score,
        limit=limit,
    )
    grasps = grasps.take(keep)
    grasps.selection = selection
    return grasps


def to_grasp_frame(
    grasps: ImportedGrasps,
    path: str | Path,
    fmt: str | None,
    *,
    gripper: GripperSpec | None = None,
    grasp_to_tool: np.ndarray | None = None,
    registry: Mapping[str, GripperSpec] | None = None,
    tool: GripperSpec | None = None,
) -> tuple[np.ndarray, GripperChoice | None]:
    """Poses (N, 4, 4) of the robot's grasp frame, and how a gripper frame was mapped.

    Args:
        grasps: As :func:`read_grasps` read them.
        path: The file (for messages).
        fmt: Its format (None: ``npy``/``npz``/``csv`` told by the suffix).
        gripper: The configured gripper (``candidates.gripper``, read), if any.
        grasp_to_tool: (4, 4) the file's frame -> the robot's grasp frame, on
            the right (``candidates.grasp_to_tool``), if given.
        registry: The shipped grippers by name, where a gripper the file names
            (or its dataset's) is looked up
            (:func:`~gcm_pipeline.config.gripper_spec.gripper_registry`).
        tool: The robot's tool (``robot.tool``, read): the gripper of a file
            that names none and has no dataset gripper.

    Returns:
        ``(poses, choice)``: ``choice`` is None for poses of the grasp frame
        (``npy``/``npz``/``csv``).

    Raises:
        InputError: The file's gripper is unknown or missing
            (:func:`~gcm_pipeline.sources.grippers.choose_gripper`).
    """
    poses = grasps.poses
    if fmt not in GRIPPER_FORMATS:
        return (poses if grasp_to_tool is None else poses @ grasp_to_tool), None
    assert fmt is not None
    known = {} if registry is None else registry
    choice = choose_gripper(
        path, fmt, gripper, grasp_to_tool is not None, grasps.gripper, known, tool
    )
    log.info("candidates: %s: gripper frame of %s", path, choice.describe())
    if grasp_to_tool is not None:
        return poses @ grasp_to_tool, choice
    assert choice.gripper is not None
    spec = {"config": gripper, "robot_tool": tool}.get(choice.chosen_by) or known[choice.gripper]
    assert spec is not None
    return poses @ spec.to_tool(grasps.convention, grasps.depth), choice


def _infer_format(path: Path) -> str:
    suffix = path.suffix.lower()
    fmt = {".npy": "npy", ".npz": "npz", ".csv": "csv", ".h5": "acronym", ".hdf5": "acronym"}
    if suffix not in fmt:
        found = sniff(path)
        looks = (
            f" (it looks like {found.description}: format: {' or '.join(found.formats)})"
            if found is not None and found.formats
            else ""
        )
        raise InputError(
            f"{path}: cannot tell the grasp file format from the suffix {clip(suffix)}; "
            f"set candidates.format to one of: acronym, csv, npy, npz{looks}",
            path=path,
            key="candidates.format",
            value=suffix,
            choices=("acronym", "csv", "npy", "npz"),
        )
    return fmt[suffix]


def load_grasp_file(
    path: str | Path,
    *,
    format: str | None = None,
    success_only: bool = False,
    limit: int | None = None,
    max_count: int = DEFAULT_MAX_CANDIDATES,
) -> np.ndarray:
    """Read grasp poses (N, 4, 4) from a file, as stored (no frame change).

    The poses of :func:`read_grasp_file` (see there for the formats).
    """
    poses, _ = read_grasp_file(
        path, format=format, success_only=success_only, limit=limit, max_count=max_count
    )
    return poses


def read_grasp_file(
    path: str | Path,
    *,
    format: str | None = None,
    success_only: bool = False,
    limit: int | None = None,
    max_count: int = DEFAULT_MAX_CANDIDATES,
) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    """Read grasp poses (N, 4, 4) and per-candidate columns from a file, as stored.

    Formats:

    - ``npy``: one array (N, 4, 4).
    - ``npz``: array ``transforms`` (or ``poses``, or the only (N, 4, 4)
      array), optional ``success`` (N,) 0/1; other 1-D arrays of N numbers or
      strings (``score``, ``id``, ...) are carried as columns.
    - ``csv``: a header row naming at least ``x,y,z,qw,qx,qy,qz`` (any order,
      case-insensitive; an optional ``success`` column); quaternions (w, x,
      y, z) are normalised if within 1e-3 of unit norm. Every other column
      (``id``, ``score``, ...) is carried as a column: integers, numbers
      (empty = NaN) or text. A UTF-8 byte order mark and blank lines are
      ignored; duplicate column names are an error.
    - ``acronym``: the ACRONYM HDF5 layout: ``grasps/transforms`` (N, 4, 4)
      gripper poses in the object mesh frame [m],
      ``grasps/qualities/flex/object_in_gripper`` (N,) 0/1 success; needs
      the optional extra ``acronym`` (h5py).

    Every format also gives ``source_id``: the grasp's 0-based row in the
    file (before ``success_only`` and ``limit``), so each candidate row of
    ``grasps.csv`` traces back to its input. Sizes are checked from the
    file's header before any array is allocated: a file of more than
    ``max_count`` grasps, or one whose header promises more data than it
    holds, is refused; so are a CSV cell longer than ``MAX_CSV_CELL`` and an
    HDF5 text declaring more than ``MAX_HDF5_TEXT`` bytes
    (:mod:`gcm_pipeline.bounds`). A file whose first bytes show another
    format is refused naming it (:mod:`gcm_pipeline.sources.files.sniff`); a grasp
    farther than ``MAX_GRASP_DISTANCE`` (1,000 m) from the origin is refused
    naming its row.

    Args:
        path: The grasp file.
        format: One of the formats above; default from the suffix.
        success_only: Keep only successful grasps (needs success labels).
        limit: Keep at most this many (the first ones, after filtering).
        max_count: Most grasps a file may hold (``candidates.max_count``).

    Returns:
        ``(poses, columns)``: (N, 4, 4) float64 rigid transforms and (N,)
        arrays keyed by column name (see
        :data:`gcm_pipeline.table.CANDIDATE_COLUMNS`).

    Raises:
        InputError: Missing, truncated or corrupt file, wrong shape or dtype,
            non-rigid matrix (names the row), a missing key, too many
            grasps, or ``success_only`` without success labels.
    """
    poses, columns, _ = read_grasp_file_gripper(
        path, format=format, success_only=success_only, limit=limit, max_count=max_count
    )
    return poses, columns


def read_grasp_file_gripper(
    path: str | Path,
    *,
    format: str | None = None,
    success_only: bool = False,
    limit: int | None = None,
    max_count: int = DEFAULT_MAX_CANDIDATES,
) -> tuple[np.ndarray, dict[str, np.ndarray], str | None]:
    """:func:`read_grasp_file`, plus the gripper the file names (ACRONYM's ``gripper/type``)."""
    poses, columns, gripper = _read_builtin(path, format, max_count)
    keep, _ = select_grasps(
        path, format, columns, columns.get("success"), success_only=success_only, limit=limit
    )
    columns = {k: v[keep] for k, v in columns.items()}
    return np.ascontiguousarray(poses[keep], dtype=float), columns, gripper


def _read_builtin(
    path: str | Path, format: str | None, max_count: int
) -> tuple[np.ndarray, dict[str, np.ndarray], str | None]:
    """Poses, columns (``source_id``, ``success``, ``score``, ...), gripper: unfiltered.

    For the built-in formats ``npy``, ``npz``, ``csv`` and ``acronym``.
    """
    path = Path(path)
    try:
        if not path.exists():
            raise InputError(f"grasp file not found: {path}")
        if not path.is_file():
            raise InputError(f"grasp file is not a file: {path}")
    except (OSError, ValueError) as exc:  # name too long, NUL byte
        raise InputError(f"grasp file {clip(str(path))}: cannot access: {exc}") from None
    fmt = format or _infer_format(path)
    check_format(path, fmt)
    gripper: str | None = None
    columns: dict[str, np.ndarray] = {}
    success: np.ndarray | None
    if fmt == "npy":
        poses, success = read_npy(path, max_count), None
    elif fmt == "npz":
        poses, success, columns = read_npz(path, max_count)
    elif fmt == "csv":
        poses, success, columns = read_csv(path, max_count)
    elif fmt == "acronym":
        poses, success, gripper = read_acronym(path, max_count)
    else:
        raise InputError(
            f"{path}: unknown grasp file format {clip(fmt)}; valid: acronym, csv, npy, npz",
            path=path,
            key="format",
            value=fmt,
            choices=("acronym", "csv", "npy", "npz"),
        )
    check_rigid(path, poses)
    if fmt != "csv":  # a CSV names the line, above
        check_positions(path, poses[:, :3, 3])
    columns = {"source_id": np.arange(len(poses), dtype=np.int64), **columns}
    if success is not None:
        columns["success"] = success
    if fmt == "acronym":  # its quality: object_in_gripper, 0/1 (see acronym.py)
        columns["score"] = np.asarray(success, dtype=np.float64)
    return np.ascontiguousarray(poses, dtype=float), columns, gripper
