"""Candidate stage: grasp candidates from a generator or a file.

The generators stand in for a grasp synthesiser. Each places ``count`` grasp
frames on the object described by the config's ``object`` section, in the
object frame, adds seeded noise and maps the poses into the world by the
object pose. A grasp pose is the pose of the robot's grasp frame
(``panda_hand_tcp`` for the Panda): origin between the fingertips, z = the
approach direction, fingers closing along y.

========================= ===================================================
source                    grasps
========================= ===================================================
``plane``                 on a flat surface (the paper's Fig. 1): positions
                          uniform in the plane's ``size``, approach from above
                          (z pointing down, along the plane's -z), a random yaw
                          in [-45, 45] deg about the approach
``cylinder_side``         a bottle grasped along its side: ``rings`` rings at
                          heights in [0.2, 0.8] of the cylinder's height
                          (default: as many as give an even spacing),
                          staggered evenly spaced angles, approach radial
                          (z toward the axis), fingers closing tangentially
                          (y along the tangent), x along the cylinder axis
``box``                   on the five faces other than the one the box stands
                          on (its frame's -z face), chosen with probability
                          proportional to their area; approach along the
                          inward face normal, fingers closing along the
                          face's shorter side, near the face's middle line
``sphere``                a Fibonacci lattice over the sphere without its
                          bottom cap (polar angle <= 120 deg); approach toward
                          the centre, fingers closing along the horizontal
                          tangent
``file``                  imported, see :func:`load_grasp_file`
========================= ===================================================

``depth`` [m] moves every generated grasp frame along its approach axis,
past the surface (default 0 for ``plane``, 0.01 m otherwise: the fingertips
reach 1 cm past the surface they approach).

Noise: ``noise.position`` [m] is the standard deviation of a Gaussian
displacement per world axis; ``noise.angle_deg`` [deg] the standard deviation
of the angle of a rotation about a uniformly random axis, applied in the grasp
frame (on the right). All randomness comes from one
:func:`numpy.random.default_rng` seeded by ``candidates.seed`` (or the top-level
``seed``), so the same config gives the same candidates.

Imported poses (``source: file``) are read as stored (:func:`load_grasp_file`),
then mapped onto the robot's grasp frame by ``grasp_to_tool`` on the right,
``T_tool = T_grasp @ grasp_to_tool``, and into the world by the object pose when
``frame: object``: ``T_world = T_object @ T_tool``. (``format: acronym`` and the
synthesisers' formats map their gripper frame by the gripper registry instead,
see :mod:`gcm_pipeline.formats`.) For poses in ACRONYM's Franka gripper frame
(origin at the hand base, z = approach, fingers closing along x: its finger
control points are at x = +-0.041 m) written as ``npy``/``npz``/``csv``, and the
Panda's ``panda_hand_tcp`` (0.1034 m further along z, fingers closing along y) use
``grasp_to_tool: {xyz: [0, 0, 0.1034], rpy_deg: [0, 0, -90]}``: the tool's y
axis is then the gripper's +x axis, its origin the midpoint of the fingertips,
its z the same approach (``tests/test_candidates.py`` checks this geometry).
``rpy_deg: [0, 0, 90]`` is the same grasp turned by 180 deg about the
approach: the symmetric hand cannot tell the two apart, but the arm reaches
them with joint 7 differing by pi, so the choice can change reachability.
Generated grasps (and the ``antipodal`` sampler's) are mapped by ``grasp_to_tool``
the same way, before the object pose: the generators make the frame of a
Panda-like TCP (z = approach, fingers closing along y, origin between the
fingertips), which another tool may need offset or turned.

Everything is vectorised: poses are (N, 4, 4) arrays until they become the
``dq`` column of a :class:`~gcm_pipeline.table.GraspTable`.
"""

from __future__ import annotations

import csv
import logging
import math
import re
from pathlib import Path
from typing import Any

import numpy as np
from scipy.spatial.transform import Rotation

from gcm_pipeline.config import CandidatesConfig, Config, ObjectConfig, takes_config
from gcm_pipeline.errors import ConfigError, InputError, clip
from gcm_pipeline.formats.importers import check_positions
from gcm_pipeline.formats.sniff import check_format
from gcm_pipeline.geometry.dualquat import dq_from_matrix
from gcm_pipeline.limits import DEFAULT_MAX_CANDIDATES, MAX_HDF5_TEXT
from gcm_pipeline.table import GraspTable

__all__ = [
    "ACRONYM_INSTALL_HINT",
    "generate_candidates",
    "grasp_poses",
    "load_grasp_file",
    "read_grasp_file",
    "poses_box",
    "poses_cylinder_side",
    "poses_plane",
    "poses_sphere",
]

log = logging.getLogger(__name__)

ACRONYM_INSTALL_HINT = 'pip install "gcm-pipeline[acronym]"'

#: Default ``depth`` [m] per generator.
_DEFAULT_DEPTH = {"plane": 0.0, "cylinder_side": 0.01, "box": 0.01, "sphere": 0.01}

#: Tolerance of the rigidity check of imported matrices.
_RIGID_TOL = 1e-4


def _frames(x: np.ndarray, y: np.ndarray, z: np.ndarray, p: np.ndarray) -> np.ndarray:
    """Stack axis columns (N, 3) and positions (N, 3) into (N, 4, 4) transforms."""
    n = p.shape[0]
    t = np.zeros((n, 4, 4))
    t[:, :3, 0] = x
    t[:, :3, 1] = y
    t[:, :3, 2] = z
    t[:, :3, 3] = p
    t[:, 3, 3] = 1.0
    return t


def poses_plane(
    count: int, size: tuple[float, float], rng: np.random.Generator, *, depth: float = 0.0
) -> np.ndarray:
    """Grasps from above on a plane (the object's xy plane), in the object frame.

    Args:
        count: Number of grasps N.
        size: Plane extent (x, y) [m], centred on the origin; positions are
            uniform in the central 80 %.
        rng: Random generator (positions and yaw).
        depth: Offset along the approach (down, -z) [m].

    Returns:
        (N, 4, 4) grasp frames: z = (0, 0, -1), yaw uniform in [-45, 45] deg.
    """
    half = 0.4 * np.asarray(size, dtype=float)
    xy = rng.uniform(-half, half, size=(count, 2))
    yaw = rng.uniform(-math.pi / 4, math.pi / 4, size=count)
    c, s = np.cos(yaw), np.sin(yaw)
    zeros = np.zeros(count)
    # Rx(pi) @ Rz(yaw): z points down, x and y rotated by the yaw.
    x = np.stack([c, -s, zeros], axis=1)
    y = np.stack([-s, -c, zeros], axis=1)
    z = np.tile([0.0, 0.0, -1.0], (count, 1))
    p = np.column_stack([xy, np.full(count, -depth)])
    return _frames(x, y, z, p)


def poses_cylinder_side(
    count: int, radius: float, height: float, *, rings: int | None = None, depth: float = 0.01
) -> np.ndarray:
    """Side grasps on a standing cylinder (axis = object z, base at z = 0).

    The grasps lie on ``rings`` rings at heights evenly spread over
    [0.2, 0.8] * ``height``; each ring holds an even share of the grasps at
    evenly spaced angles, odd rings turned by half a step (a staggered lattice
    triangulates well in the cylindrical chart).

    Args:
        count: Number of grasps N.
        radius: Cylinder radius [m].
        height: Cylinder height [m].
        rings: Number of rings (default: as many as make the spacing of the
            rings equal to the spacing along a ring, in the cylindrical chart).
        depth: How far the grasp frame lies inside the surface [m]; the frame
            sits at distance ``radius - depth`` from the axis.

    Returns:
        (N, 4, 4) grasp frames: z = toward the axis, y = tangent
        (counter-clockwise), x = the cylinder axis (up).
    """
    rho = radius - depth
    if rings is None:
        # spacing along a ring (2 pi rho / per ring) equal to the spacing of the
        # rings (0.6 h / (rings - 1)): rings (rings - 1) = 0.6 h N / (2 pi rho)
        x = 0.6 * height * count / (2 * math.pi * max(rho, 1e-9))
        rings = max(1, round(0.5 + math.sqrt(0.25 + x)))
    rings = min(rings, count)
    ring = np.arange(count) * rings // count  # ring index of each grasp, sorted
    per_ring = np.bincount(ring, minlength=rings)
    first = np.concatenate([[0], np.cumsum(per_ring)[:-1]])
    k = np.arange(count) - first[ring]
    theta = 2 * math.pi * (k + 0.5 * (ring % 2)) / per_ring[ring]
    if rings == 1:
        h = np.full(count, 0.5 * height)
    else:
        h = height * (0.2 + 0.6 * ring / (rings - 1))
    c, s = np.cos(theta), np.sin(theta)
    zeros = np.zeros(count)
    radial = np.stack([c, s, zeros], axis=1)
    tangent = np.stack([-s, c, zeros], axis=1)
    axis = np.tile([0.0, 0.0, 1.0], (count, 1))
    p = radial * rho
    p[:, 2] = h
    return _frames(axis, tangent, -radial, p)


# Faces of a box: (outward normal axis, sign); the -z face (the one the box
# stands on) is left out.
_BOX_FACES = ((0, 1.0), (0, -1.0), (1, 1.0), (1, -1.0), (2, 1.0))


def poses_box(
    count: int, size: tuple[float, float, float], rng: np.random.Generator, *, depth: float = 0.01
) -> np.ndarray:
    """Face grasps on a box centred on the origin.

    Each grasp picks one of the faces +x, -x, +y, -y, +z with probability
    proportional to its area and a position uniform in the face's central
    20 % across the closing axis and 80 % along the other side (the open
    fingers must clear the box); the frame approaches along the inward face
    normal and the fingers close along the face's shorter side.

    Args:
        count: Number of grasps N.
        size: Box edge lengths (x, y, z) [m].
        rng: Random generator (faces and positions).
        depth: Offset past the face along the approach [m].

    Returns:
        (N, 4, 4) grasp frames in the box frame.
    """
    size_arr = np.asarray(size, dtype=float)
    eye = np.eye(3)
    areas = np.array([np.prod(np.delete(size_arr, ax)) for ax, _ in _BOX_FACES])
    face = rng.choice(len(_BOX_FACES), size=count, p=areas / areas.sum())
    # across the fingers' closing axis stay near the middle (the open fingers
    # must clear the box on both sides); along the face's other side spread out
    uv = rng.uniform(-1.0, 1.0, size=(count, 2)) * [0.1, 0.4]
    x = np.empty((count, 3))
    y = np.empty((count, 3))
    z = np.empty((count, 3))
    p = np.empty((count, 3))
    for f, (ax, sign) in enumerate(_BOX_FACES):
        sel = face == f
        normal = sign * eye[ax]
        a, b = (i for i in range(3) if i != ax)
        # fingers close along the shorter in-plane side
        close, other = (a, b) if size_arr[a] <= size_arr[b] else (b, a)
        z[sel] = -normal
        y[sel] = eye[close]
        x[sel] = np.cross(eye[close], -normal)
        p[sel] = normal * (0.5 * size_arr[ax] - depth)
        p[sel, close] = uv[sel, 0] * size_arr[close]
        p[sel, other] = uv[sel, 1] * size_arr[other]
    return _frames(x, y, z, p)


def poses_sphere(count: int, radius: float, *, depth: float = 0.01) -> np.ndarray:
    """Grasps on a sphere centred on the origin, from a Fibonacci lattice.

    Args:
        count: Number of grasps N.
        radius: Sphere radius [m].
        depth: Offset past the surface along the approach [m].

    Returns:
        (N, 4, 4) grasp frames: z toward the centre, y horizontal (the local
        "east" tangent; +y of the object frame at the top pole).
    """
    # polar angle from the top pole, cos uniform over [cos(120 deg), 1]
    i = np.arange(count) + 0.5
    cos_lo = math.cos(math.radians(120.0))
    cz = 1.0 - (1.0 - cos_lo) * i / count
    sz = np.sqrt(np.clip(1.0 - cz**2, 0.0, None))
    phi = math.pi * (3.0 - math.sqrt(5.0)) * np.arange(count)
    normal = np.stack([sz * np.cos(phi), sz * np.sin(phi), cz], axis=1)
    east = np.cross([0.0, 0.0, 1.0], normal)
    norm = np.linalg.norm(east, axis=1, keepdims=True)
    east = np.where(norm > 1e-9, east / np.maximum(norm, 1e-12), [0.0, 1.0, 0.0])
    z = -normal
    x = np.cross(east, z)
    p = normal * (radius - depth)
    return _frames(x, east, z, p)


def _noise(poses: np.ndarray, position: float, angle_deg: float, rng: np.random.Generator) -> None:
    """Perturb (N, 4, 4) poses in place: Gaussian position, random-axis rotation."""
    n = poses.shape[0]
    if position > 0:
        poses[:, :3, 3] += rng.normal(0.0, position, size=(n, 3))
    if angle_deg > 0:
        axis = rng.normal(size=(n, 3))
        axis /= np.linalg.norm(axis, axis=1, keepdims=True)
        angle = rng.normal(0.0, math.radians(angle_deg), size=(n, 1))
        poses[:, :3, :3] = poses[:, :3, :3] @ Rotation.from_rotvec(axis * angle).as_matrix()


def _need_object(cfg: Config, shape: str) -> ObjectConfig:
    obj = cfg.object
    if obj is None or obj.shape != shape:
        got = "no 'object' section" if obj is None else f"object.shape {obj.shape!r}"
        raise ConfigError(
            f"candidates.source {cfg.candidates.source!r} needs object.shape {shape!r}, got {got}"
        )
    return obj


def _check_depth(depth: float, limit: float, what: str) -> None:
    """Reject a depth past the object's centre (``depth == limit`` puts it on the centre)."""
    if depth > limit:
        raise ConfigError(
            f"candidates.depth {depth:g} m puts the grasps past the object's centre: "
            f"it must not exceed the {what} ({limit:g} m)"
        )


def _generate(cfg: Config, rng: np.random.Generator) -> np.ndarray:
    """Generator poses (N, 4, 4) in the object frame."""
    c = cfg.candidates
    depth = c.depth if c.depth is not None else _DEFAULT_DEPTH[c.source]
    dims = cfg.object.dims if cfg.object is not None else None
    if dims is not None and c.source in ("cylinder_side", "sphere") and dims.radius:
        _check_depth(depth, dims.radius, "radius")
    if dims is not None and c.source == "box" and dims.size:
        _check_depth(depth, 0.5 * min(dims.size), "half of the box's smallest side")
    if c.source == "plane":
        obj = _need_object(cfg, "plane")
        assert obj.dims.size is not None
        return poses_plane(c.count, (obj.dims.size[0], obj.dims.size[1]), rng, depth=depth)
    if c.source == "cylinder_side":
        obj = _need_object(cfg, "cylinder")
        assert obj.dims.radius is not None and obj.dims.height is not None
        return poses_cylinder_side(
            c.count, obj.dims.radius, obj.dims.height, rings=c.rings, depth=depth
        )
    if c.source == "box":
        obj = _need_object(cfg, "box")
        assert obj.dims.size is not None
        sx, sy, sz = obj.dims.size
        return poses_box(c.count, (sx, sy, sz), rng, depth=depth)
    if c.source == "sphere":
        obj = _need_object(cfg, "sphere")
        assert obj.dims.radius is not None
        return poses_sphere(c.count, obj.dims.radius, depth=depth)
    raise ConfigError(f"candidates.source {c.source!r} is not a generator")  # pragma: no cover


def grasp_poses(cfg: Config) -> np.ndarray:
    """World poses (N, 4, 4) of the grasp frame for ``cfg.candidates``.

    Args:
        cfg: The full config (``candidates``, ``object`` and ``seed`` are read).

    Returns:
        (N, 4, 4) rigid transforms of the grasp frame in the world.

    Raises:
        ConfigError: A generator without a matching ``object`` section.
        InputError: An unreadable or invalid grasp file, or one whose gripper is unknown.
    """
    return _world_poses(cfg)[0]


def _world_poses(
    cfg: Config, report: dict[str, Any] | None = None
) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    """World poses (N, 4, 4) of the grasp frame and per-candidate columns, from any source."""
    from gcm_pipeline import formats

    if not formats.handles(cfg):
        return _candidate_poses(cfg)
    # synthesisers' formats (gripper frames), the antipodal sampler
    poses, columns, choice = formats.load_candidates_choice(cfg)
    if choice is not None and report is not None:
        report["grasp_frame"] = choice.as_dict() | {"describe": choice.describe()}
    if cfg.candidates.source != "file" and cfg.candidates.grasp_to_tool is not None:
        poses = poses @ cfg.candidates.grasp_to_tool.matrix()  # a sampler's grasps too
    return poses, columns


def _candidate_poses(cfg: Config) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    """World poses (N, 4, 4) of the grasp frame and per-candidate columns (files only)."""
    c = cfg.candidates
    if c.source == "file":
        assert c.path is not None
        poses, columns = read_grasp_file(
            c.path,
            format=c.format,
            success_only=c.success_only,
            limit=c.limit,
            max_count=c.max_count,
        )
        if c.grasp_to_tool is not None:
            poses = poses @ c.grasp_to_tool.matrix()
        if c.frame == "object":
            if cfg.object is None:
                raise ConfigError("candidates.frame 'object' needs an 'object' section")
            poses = cfg.object.pose.matrix() @ poses
        return poses, columns
    rng = np.random.default_rng(c.seed if c.seed is not None else cfg.seed)
    poses = _generate(cfg, rng)
    _noise(poses, c.noise.position, c.noise.angle_deg, rng)
    if c.grasp_to_tool is not None:  # generated grasps are mapped like imported ones
        poses = poses @ c.grasp_to_tool.matrix()
    assert cfg.object is not None
    return cfg.object.pose.matrix() @ poses, {}


@takes_config
def generate_candidates(cfg: Config, *, report: dict[str, Any] | None = None) -> GraspTable:
    """The candidate grasp table of a config: ``dq`` (N, 8) and per-candidate columns.

    Args:
        cfg: The full config.
        report: A dict that gets ``grasp_frame``, how a grasp file's gripper
            frame was mapped (:meth:`gcm_pipeline.formats.GripperChoice.as_dict`),
            when the file has one.

    Returns:
        A table with ``dq``: unit dual quaternions [rw, rx, ry, rz, dw, dx, dy, dz]
        of the grasp frame in the world, one row per candidate; for a grasp
        file also ``source_id`` (the row in the file) and the file's own
        columns (:func:`read_grasp_file`).

    Raises:
        ConfigError: A generator without a matching ``object`` section.
        InputError: An unreadable or invalid grasp file, a file whose gripper
            is unknown, or no grasp left.
    """
    poses, columns = _world_poses(cfg, report)
    if poses.shape[0] == 0:
        raise InputError(f"candidates: no grasp left from {_describe_source(cfg.candidates)}")
    log.info("candidates: %d from %s", poses.shape[0], _describe_source(cfg.candidates))
    return GraspTable({"dq": dq_from_matrix(poses), **columns})


def _describe_source(c: CandidatesConfig) -> str:
    if c.source == "file":
        return f"file {c.path}"
    return f"generator {c.source!r}"


# --------------------------------------------------------------------- files


def _infer_format(path: Path) -> str:
    suffix = path.suffix.lower()
    fmt = {".npy": "npy", ".npz": "npz", ".csv": "csv", ".h5": "acronym", ".hdf5": "acronym"}
    if suffix not in fmt:
        from gcm_pipeline.formats.sniff import sniff

        found = sniff(path)
        looks = (
            f" (it looks like {found.description}: format: {' or '.join(found.formats)})"
            if found is not None and found.formats
            else ""
        )
        raise InputError(
            f"{path}: cannot tell the grasp file format from the suffix {clip(suffix)}; "
            f"set candidates.format to one of: acronym, csv, npy, npz{looks}"
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
    (:mod:`gcm_pipeline.limits`). A file whose first bytes show another
    format is refused naming it (:mod:`gcm_pipeline.formats.sniff`); a grasp
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
        poses, success = _read_npy(path, max_count), None
    elif fmt == "npz":
        poses, success, columns = _read_npz(path, max_count)
    elif fmt == "csv":
        poses, success, columns = _read_csv(path, max_count)
    elif fmt == "acronym":
        poses, success, gripper = _read_acronym(path, max_count)
    else:
        raise InputError(
            f"{path}: unknown grasp file format {clip(fmt)}; valid: acronym, csv, npy, npz"
        )
    _check_rigid(path, poses)
    if fmt != "csv":  # a CSV names the line, above
        check_positions(path, poses[:, :3, 3])
    columns = {"source_id": np.arange(len(poses), dtype=np.int64), **columns}
    if success is not None:
        columns["success"] = success
    keep: np.ndarray | None = None
    if success_only:
        if success is None:
            raise InputError(
                f"{path}: candidates.success_only needs success labels, but this {fmt} file "
                "has none (npz: 'success' array, csv: 'success' column, acronym: "
                "grasps/qualities/flex/object_in_gripper)"
            )
        keep = np.flatnonzero(success)
    if limit is not None:
        keep = (np.arange(len(poses)) if keep is None else keep)[:limit]
    if keep is not None:
        poses = poses[keep]
        columns = {k: v[keep] for k, v in columns.items()}
    return np.ascontiguousarray(poses, dtype=float), columns, gripper


def _reserved_columns() -> set[str]:
    """Names a carried column must not have (grasps.csv and grasp-table columns)."""
    from gcm_pipeline.io import CSV_COLUMNS
    from gcm_pipeline.ranking.metrics import METRIC_COLUMNS

    return {
        *CSV_COLUMNS,
        *METRIC_COLUMNS.values(),
        *("dq", "vertices", "weights", "q", "top", "clearance", "margin"),
    }


def _column_name(path: Path, raw: str, taken: set[str]) -> str:
    """A carried column's name: lower case, letters/digits/_ only, not reserved or taken."""
    name = re.sub(r"[^0-9a-z_]+", "_", raw.strip().lower()).strip("_") or "column"
    if name[0].isdigit():
        name = "c_" + name
    if name in _reserved_columns() or re.fullmatch(r"q[0-9]+", name):
        raise InputError(
            f"{path}: column {clip(raw)} has the name of a grasps.csv column; rename it "
            f"(e.g. input_{name})"
        )
    if name in taken:
        raise InputError(f"{path}: two columns are named {clip(name)}; rename one of them")
    taken.add(name)
    return name


def _as_poses(path: Path, arr: np.ndarray, what: str) -> np.ndarray:
    if arr.ndim != 3 or arr.shape[1:] != (4, 4):
        raise InputError(f"{path}: {what} must have shape (N, 4, 4), got {arr.shape}")
    if arr.dtype.kind not in "fiu":
        raise InputError(f"{path}: {what} must be real numbers, got dtype {arr.dtype}")
    return np.asarray(arr, dtype=float)


def _check_count(path: Path, n: int, max_count: int) -> None:
    if n > max_count:
        raise InputError(
            f"{path}: holds {n:,} grasps, more than candidates.max_count ({max_count:,}); "
            "raise candidates.max_count to read it"
        )


def _read_npy(path: Path, max_count: int) -> np.ndarray:
    from gcm_pipeline.io import npy_header

    try:
        with path.open("rb") as fh:
            if fh.read(4) == b"PK\x03\x04":  # an npz is a zip archive
                raise InputError(f"{path}: expected a .npy array, got an archive (use format: npz)")
            fh.seek(0)
            shape, _ = npy_header(path, fh, "the array", path.stat().st_size)
            if len(shape) != 3 or shape[1:] != (4, 4):
                raise InputError(f"{path}: the array must have shape (N, 4, 4), got {shape}")
            _check_count(path, shape[0], max_count)
            fh.seek(0)
            arr = np.lib.format.read_array(fh, allow_pickle=False)
    except OSError as exc:
        raise InputError(f"{path}: cannot read: {exc.strerror or exc}") from None
    except ValueError as exc:
        raise InputError(f"{path}: not a readable .npy array: {clip(str(exc))}") from None
    return _as_poses(path, arr, "the array")


#: Bytes per grasp an .npz may hold (a 128-byte pose and some columns).
_NPZ_BYTES_PER_GRASP = 256


def _read_npz(
    path: Path, max_count: int
) -> tuple[np.ndarray, np.ndarray | None, dict[str, np.ndarray]]:
    from gcm_pipeline.io import read_npz

    arrays = read_npz(
        path,
        max_bytes=max_count * _NPZ_BYTES_PER_GRASP,
        keep=lambda name, shape, dtype: len(shape) in (1, 3),
    )
    poses_name = _npz_poses_name(path, {k: (v.shape, v.dtype) for k, v in arrays.items()})
    poses = _as_poses(path, arrays.pop(poses_name), f"array {poses_name!r}")
    _check_count(path, len(poses), max_count)
    success = arrays.pop("success", None)
    if success is not None:
        success = _success(path, success, poses.shape[0], "array 'success'")
    columns: dict[str, np.ndarray] = {}
    taken: set[str] = {"source_id", "success"}
    for name, values in arrays.items():
        if values.ndim != 1 or len(values) != len(poses) or values.dtype.kind not in "biufU":
            log.info(
                "%s: array %r %s is not one value per grasp; not read", path, name, values.shape
            )
            continue
        columns[_column_name(path, name, taken)] = values
    return poses, success, columns


def _npz_poses_name(path: Path, headers: dict[str, tuple[tuple[int, ...], Any]]) -> str:
    for name in ("transforms", "poses"):
        if name in headers:
            return name
    three_d = [k for k, (shape, _) in headers.items() if len(shape) == 3]
    if len(three_d) != 1:
        names = ", ".join(clip(k, 40) for k in list(headers)[:20]) or "none"
        raise InputError(f"{path}: expected an array 'transforms' (N, 4, 4); arrays: {names}")
    return three_d[0]


def _success(path: Path, values: np.ndarray, n: int, what: str) -> np.ndarray:
    values = np.asarray(values).reshape(-1)
    if values.shape[0] != n:
        raise InputError(f"{path}: {what} has {values.shape[0]} values, expected {n}")
    if values.dtype.kind not in "biuf":
        raise InputError(f"{path}: {what} must be 0/1 values, got dtype {values.dtype}")
    return values.astype(float) > 0.5


_CSV_POSE = ("x", "y", "z", "qw", "qx", "qy", "qz")
#: Most columns of a grasp CSV.
_MAX_CSV_COLUMNS = 1000


def _refuse_nul(path: Path, chunk: int = 1 << 22) -> None:
    """Raise InputError at the first NUL character of a CSV file.

    NumPy's strings drop trailing NULs (a cell ``0`` + NUL read as 0) and a NUL
    inside a text column would be carried into grasps.csv.
    """
    line = 1
    try:
        with path.open("rb") as fh:
            while data := fh.read(chunk):
                at = data.find(b"\0")
                if at >= 0:
                    line += data.count(b"\n", 0, at)
                    raise InputError(f"{path}:{line}: NUL character in a CSV file")
                line += data.count(b"\n")
    except OSError as exc:
        raise InputError(f"{path}: cannot read CSV: {clip(str(exc))}") from None


def _read_csv(
    path: Path, max_count: int
) -> tuple[np.ndarray, np.ndarray | None, dict[str, np.ndarray]]:
    from gcm_pipeline.io import check_csv_cells

    rows: list[list[str]] = []
    lines: list[int] = []
    _refuse_nul(path)
    try:
        with path.open(newline="", encoding="utf-8-sig") as fh:
            reader = csv.reader(fh)
            header: list[str] | None = None
            for row in reader:
                if not any(cell.strip() for cell in row):
                    continue  # blank line
                if header is None:
                    header = row
                    if len(header) > _MAX_CSV_COLUMNS:
                        raise InputError(
                            f"{path}: header has {len(header):,} columns, at most "
                            f"{_MAX_CSV_COLUMNS} are read"
                        )
                    continue
                if len(rows) >= max_count:
                    _check_count(path, len(rows) + 1, max_count)
                check_csv_cells(path, reader.line_num, header, row)
                rows.append(row)
                lines.append(reader.line_num)
    except UnicodeDecodeError as exc:
        raise InputError(f"{path}: not UTF-8 text ({exc.reason} at byte {exc.start})") from None
    except (OSError, csv.Error) as exc:
        raise InputError(f"{path}: cannot read CSV: {clip(str(exc))}") from None
    if header is None:
        raise InputError(f"{path}: empty CSV; expected a header row with {','.join(_CSV_POSE)}")
    names = [h.strip().lower() for h in header]
    seen: set[str] = set()
    for name in names:
        if name in seen:
            raise InputError(f"{path}: the header names column {clip(name)} twice")
        seen.add(name)
    missing = [c for c in _CSV_POSE if c not in names]
    if missing:
        raise InputError(
            f"{path}: CSV header lacks column(s) {', '.join(missing)}; "
            f"expected {','.join(_CSV_POSE)} (got {clip(','.join(names))})"
        )
    width = len(names)
    for row, line in zip(rows, lines, strict=True):
        if len(row) != width:
            raise InputError(f"{path}:{line}: row has {len(row)} fields, the header has {width}")
    # Python strings, not a fixed-width array: that is as wide as the longest cell in every cell
    cells = np.empty((len(rows), width), dtype=object)
    if rows:
        cells[:] = rows
    values = np.empty((len(rows), 7))
    for k, c in enumerate(_CSV_POSE):
        values[:, k] = _csv_floats(path, cells[:, names.index(c)], c, lines)
    if not np.all(np.isfinite(values)):
        i, k = (int(a[0]) for a in np.nonzero(~np.isfinite(values)))
        raise InputError(
            f"{path}:{lines[i]}: column {_CSV_POSE[k]!r}: non-finite value {values[i, k]!r}"
        )
    check_positions(path, values[:, :3], lambda i: f"{path}:{lines[i]}")
    quat = values[:, 3:]
    norm = np.linalg.norm(quat, axis=1)
    bad = np.flatnonzero(np.abs(norm - 1.0) > 1e-3)
    if bad.size:
        raise InputError(
            f"{path}:{lines[int(bad[0])]}: quaternion (qw,qx,qy,qz) has norm "
            f"{norm[bad[0]]:.6g}, expected 1"
        )
    quat = quat / norm[:, None]
    poses = np.zeros((values.shape[0], 4, 4))
    poses[:, :3, :3] = Rotation.from_quat(quat[:, [1, 2, 3, 0]]).as_matrix()
    poses[:, :3, 3] = values[:, :3]
    poses[:, 3, 3] = 1.0
    success = None
    if "success" in names:
        success = _csv_floats(path, cells[:, names.index("success")], "success", lines) > 0.5
    columns: dict[str, np.ndarray] = {}
    taken: set[str] = {"source_id", "success"}
    for k, raw in enumerate(header):
        if names[k] in _CSV_POSE or names[k] == "success":
            continue
        columns[_column_name(path, raw, taken)] = _csv_column(cells[:, k])
    return poses, success, columns


def _csv_floats(path: Path, col: np.ndarray, name: str, lines: list[int]) -> np.ndarray:
    out = np.empty(len(col))
    for i, text in enumerate(col.tolist()):
        try:
            out[i] = float(text)
        except ValueError:
            raise InputError(
                f"{path}:{lines[i]}: column {name!r}: not a number: {clip(text)}"
            ) from None
    return out


def _csv_column(col: np.ndarray) -> np.ndarray:
    """A carried CSV column: int64 if all integers, float64 if numbers (empty: NaN), else text.

    ``col`` holds Python strings (of at most ``MAX_CSV_CELL`` characters).
    """
    stripped = [t.strip() for t in col.tolist()]
    try:
        if stripped and all(re.fullmatch(r"[-+]?[0-9]{1,18}", t) for t in stripped):
            return np.array([int(t) for t in stripped], dtype=np.int64)
        return np.array([float(t) if t else np.nan for t in stripped], dtype=np.float64)
    except ValueError:
        return np.array(col.tolist(), dtype=str).reshape(len(stripped))


#: A child reading an ACRONYM file gets this long [s], plus a second per
#: ``_HDF5_BYTES_PER_SECOND`` of file, before the file counts as corrupt: the HDF5
#: library can loop forever on a damaged file (seen: a damaged variable-length string).
_HDF5_SECONDS = 10.0
_HDF5_BYTES_PER_SECOND = 20e6


def _read_acronym(path: Path, max_count: int) -> tuple[np.ndarray, np.ndarray, str | None]:
    """Read an ACRONYM file in a forked child process where one can be forked.

    The HDF5 library can crash the whole process (a segmentation fault) or
    loop forever on a corrupt file, e.g. when it follows a damaged
    variable-length string; in a child, that crash or a read that does not
    finish in time becomes an :class:`InputError` naming the file.
    """
    try:
        import h5py  # noqa: F401
    except ImportError:
        raise InputError(
            f"{path}: reading ACRONYM HDF5 files needs h5py: {ACRONYM_INSTALL_HINT}"
        ) from None
    import multiprocessing as mp
    import signal

    if "fork" not in mp.get_all_start_methods():  # pragma: no cover - not POSIX
        return _read_acronym_here(path, max_count)
    ctx = mp.get_context("fork")
    receive, send = ctx.Pipe(duplex=False)
    try:
        limit = _HDF5_SECONDS + path.stat().st_size / _HDF5_BYTES_PER_SECOND
    except OSError:
        limit = _HDF5_SECONDS
    child = ctx.Process(target=_acronym_child, args=(send, path, max_count), daemon=True)
    child.start()
    send.close()
    late, answered = False, False
    try:
        late = not receive.poll(limit)
        result = None if late else receive.recv()
        answered = not late
    except EOFError:
        result, answered = None, True
    finally:
        receive.close()
        child.join(timeout=5.0 if answered else 0)
        if child.is_alive():  # looping in HDF5, or the caller was interrupted
            child.kill()
            child.join()
    if late:
        raise InputError(
            f"{path}: the HDF5 library did not finish reading it in {limit:.0f} s; "
            "the file is corrupt"
        )
    if result is None:
        code = child.exitcode or 0
        what = signal.Signals(-code).name if code < 0 else f"exit status {code}"
        raise InputError(
            f"{path}: reading it crashed the HDF5 library ({what}); the file is corrupt"
        )
    if result[0] == "error":
        raise InputError(result[1])
    return result[1], result[2], result[3]


def _acronym_child(send: Any, path: Path, max_count: int) -> None:
    """In the child: send ``("ok", poses, success, gripper)`` or ``("error", message)``."""
    try:
        send.send(("ok", *_read_acronym_here(path, max_count)))
    except InputError as exc:
        send.send(("error", str(exc)))
    except BaseException as exc:  # anything else is reported, not raised in the child
        send.send(("error", f"{path}: corrupt or unreadable HDF5 file: {clip(str(exc))}"))
    finally:
        send.close()


def _read_acronym_here(path: Path, max_count: int) -> tuple[np.ndarray, np.ndarray, str | None]:
    """Poses, success labels and ``gripper/type`` (e.g. ``panda``, or None) of an ACRONYM file."""
    import h5py

    where = "the file"
    try:
        with h5py.File(path, "r") as fh:
            datasets = {}
            for key in ("grasps/transforms", "grasps/qualities/flex/object_in_gripper"):
                where = key
                if key not in fh:
                    raise InputError(f"{path}: not an ACRONYM grasp file: missing dataset {key!r}")
                node = fh[key]
                if not isinstance(node, h5py.Dataset):
                    raise InputError(f"{path}: {key} is a {type(node).__name__}, not a dataset")
                if node.dtype.kind not in "biuf":
                    raise InputError(f"{path}: {key} must hold numbers, got dtype {node.dtype}")
                datasets[key] = node
            where = "grasps/transforms"
            tf = datasets["grasps/transforms"]
            if len(tf.shape) != 3 or tf.shape[1:] != (4, 4):
                raise InputError(
                    f"{path}: grasps/transforms must have shape (N, 4, 4), got {tf.shape}"
                )
            _check_count(path, tf.shape[0], max_count)
            poses = _as_poses(path, np.asarray(tf[()]), "grasps/transforms")
            where = "grasps/qualities/flex/object_in_gripper"
            quality = datasets[where]
            if quality.size != poses.shape[0]:
                raise InputError(
                    f"{path}: {where} has {quality.size} values, expected {poses.shape[0]}"
                )
            success = _success(path, np.asarray(quality[()]), poses.shape[0], where)
            where = "object"
            name, scale = _acronym_object(path, fh, h5py)
            where = "gripper/type"
            gripper = _h5_text(path, fh, h5py, "gripper/type")
    except InputError:
        raise
    except (OSError, KeyError, RuntimeError, ValueError, TypeError) as exc:
        raise InputError(
            f"{path}: corrupt or unreadable HDF5 file (at {where}): {clip(str(exc))}"
        ) from None
    if name is not None:
        log.info("%s: ACRONYM grasps of %s (scale %g)", path, name, scale)
    return poses, success, gripper


def _h5_small(path: Path, node: Any, h5py: Any, key: str, what: str, max_bytes: int) -> Any:
    """The dataset ``key`` read whole, after its declared size is checked.

    A dataset's size comes from its header, not from the bytes in the file
    (an unwritten dataset reads as fill values): an 8 KiB file can declare a
    1.5 GB string, which reading would allocate.

    Raises:
        InputError: Not a dataset, or more than ``max_bytes`` declared.
    """
    if not isinstance(node, h5py.Dataset):
        raise InputError(f"{path}: {key} must be {what}, got a {type(node).__name__}")
    declared = int(np.prod(node.shape, dtype=object)) * node.dtype.itemsize
    if declared > max_bytes:
        raise InputError(
            f"{path}: {key} declares {declared:,} bytes (shape {node.shape}, dtype "
            f"{node.dtype}); {what} takes at most {max_bytes:,}: the file is corrupt"
        )
    return node[()]


def _h5_text(path: Path, fh: Any, h5py: Any, key: str) -> str | None:
    """The text stored at ``key`` (None when the file has no ``key``), at most ``MAX_HDF5_TEXT``."""
    if key not in fh:
        return None
    raw = _h5_small(path, fh[key], h5py, key, "a text", MAX_HDF5_TEXT)
    if isinstance(raw, np.ndarray) and raw.size == 1:
        raw = raw.reshape(-1)[0]
    if isinstance(raw, bytes) and len(raw) <= MAX_HDF5_TEXT:
        try:
            raw = raw.decode("utf-8")
        except UnicodeDecodeError:
            raw = None
    if not isinstance(raw, str) or len(raw) > MAX_HDF5_TEXT:
        raise InputError(f"{path}: {key} must be a text, got {clip(raw)}")
    return raw


def _acronym_object(path: Path, fh: Any, h5py: Any) -> tuple[str | None, float]:
    """``object/file`` (text) and ``object/scale`` (a number) of an ACRONYM file."""
    name = _h5_text(path, fh, h5py, "object/file")
    scale = 1.0
    if "object/scale" in fh:
        raw = _h5_small(path, fh["object/scale"], h5py, "object/scale", "a number", 16)
        if isinstance(raw, np.ndarray) and raw.size == 1:
            raw = raw.reshape(-1)[0]
        if isinstance(raw, (bool, np.bool_)) or not isinstance(raw, (int, float, np.number)):
            raise InputError(f"{path}: object/scale must be a number, got {clip(raw)}")
        scale = float(raw)
        if not (math.isfinite(scale) and scale > 0):
            raise InputError(f"{path}: object/scale must be a positive number, got {scale!r}")
    return name, scale


def _check_rigid(path: Path, poses: np.ndarray) -> None:
    """Raise naming the first row that is not a finite rigid transform."""
    if poses.shape[0] == 0:
        return
    finite = np.all(np.isfinite(poses), axis=(1, 2))
    rot = np.where(finite[:, None, None], poses[:, :3, :3], 0.0)
    with np.errstate(over="ignore", invalid="ignore"):  # huge entries: inf, not a warning
        ortho = np.abs(rot @ np.swapaxes(rot, 1, 2) - np.eye(3)).max(axis=(1, 2))
        det = np.linalg.det(rot)
        bottom = np.abs(poses[:, 3] - [0.0, 0.0, 0.0, 1.0]).max(axis=1)
    ok = finite & (ortho < _RIGID_TOL) & (det > 0) & (bottom < _RIGID_TOL)
    bad = np.flatnonzero(~ok)
    if bad.size == 0:
        return
    i = int(bad[0])
    if not finite[i]:
        why = "has non-finite entries"
    elif bottom[i] >= _RIGID_TOL:
        why = f"has last row {poses[i, 3].tolist()}, expected [0, 0, 0, 1]"
    elif ortho[i] >= _RIGID_TOL:
        why = f"has a non-orthonormal rotation (|R R^T - I| = {ortho[i]:.3g})"
    else:
        why = "has a reflection (det R < 0)"
    more = f" ({bad.size} bad rows in all)" if bad.size > 1 else ""
    raise InputError(f"{path}: grasp {i} (0-based row) is not a rigid transform: {why}{more}")
