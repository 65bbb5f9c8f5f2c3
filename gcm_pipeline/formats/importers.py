"""Importers of grasp synthesisers' files: GraspGen, Contact-GraspNet, GraspNet-1Billion.

Each reader returns the poses exactly as the file stores them (the file's
own gripper frame, in the file's frame of reference) plus the per-candidate
values the file carries; :func:`gcm_pipeline.formats.load_candidates` maps
them onto the robot's grasp frame (:mod:`gcm_pipeline.formats.grippers`) and
into the world.

========================= ============================================================
format                    layout read
========================= ============================================================
``graspgen``              GraspGen's grasp data (JSON or YAML): ``grasps.transforms``
                          (N, 4, 4) poses of the gripper's base link in the object
                          mesh frame, optional ``grasps.object_in_gripper`` (N,)
                          success mask and ``grasps.confidences`` (N,),
                          ``object.file`` / ``object.scale``, an optional
                          ``gripper`` (a name or ``{name: ...}``); or GraspGen's
                          inference output in the ``isaac_grasp`` YAML format
                          (``format: isaac_grasp``, ``grasps: {name: {confidence,
                          position: [x, y, z], orientation: {w, xyz: [x, y, z]}}}``)
``contact_graspnet``      Contact-GraspNet's ``predictions_*.npz``: dicts keyed by
                          segment id (stored as pickled 0-d object arrays):
                          ``pred_grasps_cam`` (M, 4, 4) gripper base poses in the
                          camera frame (OpenCV: x right, y down, z forward),
                          ``scores`` (M,), ``contact_pts`` (M, 3), optional
                          ``gripper_openings`` (M,) [m]; plain arrays (no dict)
                          are one segment (-1)
``graspnet``              GraspNet-1Billion / AnyGrasp ``GraspGroup`` arrays (``.npy``
                          or the only / ``grasp_group_array`` array of an ``.npz``):
                          rows of 17 values ``[score, width, height, depth,
                          R (9, row-major), t (3), object_id]`` [m]
========================= ============================================================

Sources: GraspGen's ``docs/GRASP_DATASET_FORMAT.md`` and its
``save_to_isaac_grasp_format``; the Isaac Sim grasp-editor page on the
``isaac_grasp`` file; Contact-GraspNet's ``inference.py`` (``np.savez`` of
``pred_grasps_cam``, ``scores``, ``contact_pts``; later versions add
``gripper_openings``); graspnetAPI's ``grasp.py`` (``GRASP_ARRAY_LEN = 17``
and the accessors ``rotation_matrices = rows[:, 4:13].reshape(-1, 3, 3)``,
``translations = rows[:, 13:16]``).

Contact-GraspNet stores its dicts with pickle. They are read by a restricted
unpickler that only builds NumPy arrays, dtypes and scalars (besides plain
dicts, lists, numbers and strings), so a prediction file cannot run code.
"""

from __future__ import annotations

import json
import logging
import pickle
import zipfile
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from scipy.spatial.transform import Rotation

from gcm_pipeline.errors import InputError, clip
from gcm_pipeline.formats.sniff import check_format, sniff
from gcm_pipeline.limits import DEFAULT_MAX_CANDIDATES, MAX_GRASP_DISTANCE

__all__ = [
    "IMPORT_FORMATS",
    "ImportedGrasps",
    "read_contact_graspnet",
    "read_graspgen",
    "read_graspnet",
]

log = logging.getLogger(__name__)

#: Formats read here, with the gripper-frame convention of their poses.
IMPORT_FORMATS: dict[str, str] = {
    "graspgen": "base",
    "contact_graspnet": "base",
    "graspnet": "center",
}

_RIGID_TOL = 1e-4

#: Bytes a grasp may take in a text (JSON/YAML) file, and the slack on top (object,
#: gripper and comments): a file larger than ``max_count`` grasps can fill is refused.
_TEXT_BYTES_PER_GRASP = 2048
#: Bytes a grasp may take in a binary (.npy/.npz) file: a pose, scores, contacts,
#: openings and pickle framing.
_BINARY_BYTES_PER_GRASP = 512
_SLACK_BYTES = 1 << 20
#: YAML or JSON values a grasp may take (YAML after aliases; 16 for its pose and a few more).
_YAML_VALUES_PER_GRASP = 64


def _check_count(path: Path, n: int, max_count: int) -> None:
    if n > max_count:
        raise InputError(
            f"{path}: holds {n:,} grasps, more than candidates.max_count ({max_count:,}); "
            "raise candidates.max_count to read it"
        )


def _check_bytes(path: Path, size: int, max_count: int, per_grasp: int, what: str) -> None:
    limit = max_count * per_grasp + _SLACK_BYTES
    if size > limit:
        raise InputError(
            f"{path}: {what} take {size:,} bytes, more than {max_count:,} grasps "
            f"(candidates.max_count) need (at most {limit:,}); raise candidates.max_count "
            "to read it"
        )


@dataclass
class ImportedGrasps:
    """Grasps as a file stores them.

    Attributes:
        poses: (N, 4, 4) poses of the file's gripper frame [m].
        convention: The gripper-frame convention (``base`` or ``center``).
        columns: Per-candidate columns (N,) to carry through (``score``,
            ``width``, ``source_id``, ``segment``, ``object_id``).
        success: (N,) bool success labels, or None.
        depth: (N,) ``center`` convention: fingertip depth past the centre [m].
        gripper: The gripper named in the file, if any.
    """

    poses: np.ndarray
    convention: str
    columns: dict[str, np.ndarray] = field(default_factory=dict)
    success: np.ndarray | None = None
    depth: np.ndarray | None = None
    gripper: str | None = None

    def take(self, index: np.ndarray) -> ImportedGrasps:
        """The rows selected by an integer index or boolean mask."""
        return ImportedGrasps(
            poses=self.poses[index],
            convention=self.convention,
            columns={k: v[index] for k, v in self.columns.items()},
            success=None if self.success is None else self.success[index],
            depth=None if self.depth is None else self.depth[index],
            gripper=self.gripper,
        )


def check_positions(
    path: Path, positions: np.ndarray, where: Callable[[int], str] | None = None
) -> None:
    """Refuse a grasp farther than :data:`~gcm_pipeline.limits.MAX_GRASP_DISTANCE` from the origin.

    A robot's world is metres across; a grasp 1e25 m away is a unit or
    export mistake, and further on it only breaks the manifold's geometry.

    Args:
        path: The file (for messages).
        positions: (N, 3) finite grasp positions as the file stores them [m].
        where: How a message names row ``i`` (default ``"<path>: grasp <i> (0-based)"``).

    Raises:
        InputError: Names the first such row and its position (attributes
            ``path``, ``row`` (0-based), ``value``: its distance [m]).
    """
    with np.errstate(over="ignore"):
        dist = np.linalg.norm(np.asarray(positions, dtype=float).reshape(-1, 3), axis=1)
    far = np.flatnonzero(~(dist <= MAX_GRASP_DISTANCE))
    if far.size:
        i = int(far[0])
        name = where(i) if where is not None else f"{path}: grasp {i} (0-based)"
        more = f" ({far.size:,} such grasps)" if far.size > 1 else ""
        xyz = ", ".join(f"{v:.6g}" for v in np.asarray(positions, dtype=float).reshape(-1, 3)[i])
        err = InputError(
            f"{name}: position ({xyz}) is {dist[i]:.3g} m from the file's origin, farther "
            f"than {MAX_GRASP_DISTANCE:g} m (gcm_pipeline.limits.MAX_GRASP_DISTANCE): not a "
            f"grasp in a robot's world; are the units metres?{more}"
        )
        err.path, err.row, err.value = path, i, float(dist[i])  # type: ignore[attr-defined]
        raise err


def check_poses(path: Path, poses: np.ndarray, what: str) -> np.ndarray:
    """Return ``poses`` as float (N, 4, 4) or raise naming the first non-rigid row."""
    arr = np.asarray(poses)
    if arr.ndim != 3 or arr.shape[1:] != (4, 4):
        raise InputError(f"{path}: {what} must have shape (N, 4, 4), got {arr.shape}")
    if arr.dtype.kind not in "fiu":
        raise InputError(f"{path}: {what} must be real numbers, got dtype {arr.dtype}")
    arr = arr.astype(float)
    if len(arr) == 0:
        return arr
    rot = arr[:, :3, :3]
    with np.errstate(invalid="ignore"):
        err = np.abs(rot @ np.swapaxes(rot, 1, 2) - np.eye(3)).max(axis=(1, 2))
        err = np.maximum(err, np.abs(arr[:, 3] - [0.0, 0.0, 0.0, 1.0]).max(axis=1))
        det = np.linalg.det(np.nan_to_num(rot))
    bad = np.flatnonzero(~(np.isfinite(arr).all(axis=(1, 2)) & (err < _RIGID_TOL) & (det > 0)))
    if bad.size:
        more = f" ({bad.size} bad rows in all)" if bad.size > 1 else ""
        raise InputError(
            f"{path}: {what}: grasp {int(bad[0])} (0-based) is not a rigid transform{more}"
        )
    check_positions(path, arr[:, :3, 3])
    return arr


# ----------------------------------------------------------------- GraspGen


def _read_structured(path: Path, max_count: int) -> Any:
    from gcm_pipeline.safe_yaml import load_yaml

    try:
        _check_bytes(path, path.stat().st_size, max_count, _TEXT_BYTES_PER_GRASP, "its grasps")
        text = path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise InputError(f"{path}: cannot read: {exc}") from None
    max_values = max(_YAML_VALUES_PER_GRASP * max_count, 100_000)
    if path.suffix.lower() == ".json":
        # a value takes up to ~70 bytes parsed ("[]," is 3 bytes of text and a list of 56):
        # counted from the separators before anything is built
        values = 1 + text.count(",") + text.count("[") + text.count("{")
        if values > max_values:
            raise InputError(
                f"{path}: holds about {values:,} JSON values, more than {max_count:,} grasps "
                f"(candidates.max_count) need (at most {max_values:,}); raise "
                "candidates.max_count to read it"
            )
        try:
            return json.loads(text)
        except ValueError as exc:
            raise InputError(f"{path}: not valid JSON: {' '.join(str(exc).split())}") from None
        except RecursionError:
            raise InputError(f"{path}: not a GraspGen grasp file: JSON nested too deeply") from None
    return load_yaml(text.removeprefix("\ufeff"), str(path), InputError, max_values=max_values)


def _vector(path: Path, value: Any, n: int, what: str) -> np.ndarray:
    try:
        arr = np.asarray(value, dtype=float).reshape(-1)
    except (TypeError, ValueError):
        raise InputError(f"{path}: {what} must be numbers") from None
    if arr.shape[0] != n:
        raise InputError(f"{path}: {what} has {arr.shape[0]} values, expected {n}")
    return arr


def read_graspgen(path: str | Path, *, max_count: int = DEFAULT_MAX_CANDIDATES) -> ImportedGrasps:
    """Read a GraspGen grasp file (JSON/YAML dataset layout or ``isaac_grasp`` YAML).

    Args:
        path: The file.
        max_count: Most grasps the file may hold (``candidates.max_count``);
            a larger file is refused before it is parsed.

    Returns:
        Gripper base-link poses (``base`` convention, object mesh frame) with
        ``score`` (the confidences, when the file has them) and ``source_id``
        (the grasp's index in the file); ``success`` from
        ``object_in_gripper``.

    Raises:
        InputError: Unreadable file, a layout that is not GraspGen's, bad values.
    """
    path = Path(path)
    check_format(path, "graspgen")
    data = _read_structured(path, max_count)
    if not isinstance(data, dict):
        raise InputError(
            f"{path}: not a GraspGen grasp file: expected a mapping with 'grasps', "
            f"got {type(data).__name__}"
        )
    if data.get("format") == "isaac_grasp":
        return _read_isaac_grasp(path, data, max_count)
    grasps = data.get("grasps")
    if not isinstance(grasps, dict) or "transforms" not in grasps:
        raise InputError(
            f"{path}: not a GraspGen grasp file: expected 'grasps: {{transforms: [...]}}' "
            f"or 'format: isaac_grasp' (keys: {', '.join(map(str, data)) or 'none'})"
        )
    if isinstance(grasps["transforms"], list):
        _check_count(path, len(grasps["transforms"]), max_count)
    try:
        raw = np.asarray(grasps["transforms"], dtype=float)
    except (TypeError, ValueError):
        raise InputError(f"{path}: grasps.transforms must be (N, 4, 4) numbers") from None
    if raw.size == 0:
        raw = raw.reshape(0, 4, 4)
    poses = check_poses(path, raw, "grasps.transforms")
    n = len(poses)
    columns: dict[str, np.ndarray] = {}
    for key in ("confidences", "confidence", "scores"):
        if key in grasps:
            columns["score"] = _vector(path, grasps[key], n, f"grasps.{key}")
            break
    success = None
    if "object_in_gripper" in grasps:
        success = _vector(path, grasps["object_in_gripper"], n, "grasps.object_in_gripper") > 0.5
    columns["source_id"] = np.arange(n, dtype=np.int64)
    obj = data.get("object")
    if isinstance(obj, dict) and "file" in obj:
        log.info("%s: GraspGen grasps of %s (scale %s)", path, obj.get("file"), obj.get("scale"))
    gripper = data.get("gripper")
    if isinstance(gripper, dict):
        gripper = gripper.get("name")
    return ImportedGrasps(
        poses, "base", columns, success, gripper=str(gripper) if gripper else None
    )


def _read_isaac_grasp(path: Path, data: dict[str, Any], max_count: int) -> ImportedGrasps:
    grasps = data.get("grasps")
    if not isinstance(grasps, dict):
        raise InputError(f"{path}: isaac_grasp file without a 'grasps' mapping")
    n = len(grasps)
    _check_count(path, n, max_count)
    pos = np.empty((n, 3))
    quat = np.empty((n, 4))  # w, x, y, z
    score = np.full(n, np.nan)
    for i, (name, g) in enumerate(grasps.items()):
        try:
            pos[i] = np.asarray(g["position"], dtype=float).reshape(3)
            o = g["orientation"]
            quat[i, 0] = float(o["w"])
            quat[i, 1:] = np.asarray(o["xyz"], dtype=float).reshape(3)
            if "confidence" in g:
                score[i] = float(g["confidence"])
        except (KeyError, TypeError, ValueError):
            raise InputError(
                f"{path}: grasp {clip(name)}: expected position: [x, y, z] and "
                "orientation: {w: .., xyz: [x, y, z]}"
            ) from None
        if not np.isfinite(pos[i]).all():
            raise InputError(
                f"{path}: grasp {clip(name)}: position {pos[i].tolist()} is not finite"
            )
    check_positions(path, pos, lambda i: f"{path}: grasp {clip(list(grasps)[i])}")
    norm = np.linalg.norm(quat, axis=1)
    bad = np.flatnonzero(~np.isfinite(norm) | (np.abs(norm - 1.0) > 1e-3))
    if bad.size:
        name = list(grasps)[int(bad[0])]
        raise InputError(
            f"{path}: grasp {clip(name)}: orientation has norm {norm[bad[0]]:.6g}, not 1"
        )
    poses = np.zeros((n, 4, 4))
    if n:
        poses[:, :3, :3] = Rotation.from_quat((quat / norm[:, None])[:, [1, 2, 3, 0]]).as_matrix()
    poses[:, :3, 3] = pos
    poses[:, 3, 3] = 1.0
    columns = {"score": score, "source_id": np.arange(n, dtype=np.int64)}
    return ImportedGrasps(poses, "base", columns)


# --------------------------------------------------------- Contact-GraspNet

_SAFE_GLOBALS = {
    ("numpy.core.multiarray", "_reconstruct"),
    ("numpy._core.multiarray", "_reconstruct"),
    ("numpy.core.multiarray", "scalar"),
    ("numpy._core.multiarray", "scalar"),
    ("numpy", "ndarray"),
    ("numpy", "dtype"),
}


def _empty_reconstruct(subtype: Any, shape: Any, dtype: Any) -> np.ndarray:
    """NumPy's pickled-array constructor, for the empty arrays a pickle starts from.

    A pickled array is built as an empty array whose state (shape and data)
    is then set from the pickle's bytes; a pickle that asks the constructor
    itself for a large array would allocate memory the file never held.
    """
    if subtype is not np.ndarray or int(np.prod(shape, dtype=object)) != 0:
        raise pickle.UnpicklingError("refusing a pickled array that is not built from its data")
    return np.ndarray.__new__(subtype, shape, dtype)


#: Steps (opcodes) a pickled member may take: a dict of arrays takes a few per array, while
#: each step may add a reference (DUP, GET: one byte of file, 8 of memory), so the count,
#: not the file's size, bounds what unpickling builds.
_MAX_PICKLE_STEPS = 1_000_000


class _TooManySteps(Exception):
    pass


def _counted(step: Callable[[Any], None]) -> Callable[[Any], None]:
    def run(self: _ArrayUnpickler) -> None:
        self.steps_left -= 1
        if self.steps_left < 0:
            raise _TooManySteps
        step(self)

    return run


class _ArrayUnpickler(pickle._Unpickler):
    """Unpickles NumPy arrays, dtypes and scalars in plain containers; nothing else.

    The pure-Python unpickler, each opcode counted (at most :data:`_MAX_PICKLE_STEPS`).
    """

    dispatch = {k: _counted(f) for k, f in pickle._Unpickler.dispatch.items()}

    def __init__(self, file: Any) -> None:
        super().__init__(file)
        self.steps_left = _MAX_PICKLE_STEPS

    def find_class(self, module: str, name: str) -> Any:
        if (module, name) not in _SAFE_GLOBALS:
            raise pickle.UnpicklingError(f"refusing to load {module}.{name}")
        if name == "_reconstruct":
            return _empty_reconstruct
        return super().find_class(module, name)


def _read_npz_members(path: Path, max_count: int) -> dict[str, Any]:
    """Every array of an ``.npz``; object arrays through :class:`_ArrayUnpickler`.

    Sizes are checked before anything is read: all members together at most
    what ``max_count`` grasps take, and each plain array's header against
    the bytes its member holds.
    """
    from gcm_pipeline.rundir.arrays import npy_header

    out: dict[str, Any] = {}
    # numbers the pickled members may expand to: a pickle refers to one list or array
    # many times for a few bytes each, so its size on disk does not bound them
    budget = max_count * (_BINARY_BYTES_PER_GRASP // 8) + _SLACK_BYTES // 8
    values = 0
    try:
        with zipfile.ZipFile(path) as zf:
            infos = [i for i in zf.infolist() if i.filename.endswith(".npy")]
            total = sum(i.file_size for i in infos)
            _check_bytes(path, total, max_count, _BINARY_BYTES_PER_GRASP, "its arrays")
            for info in infos:
                name = info.filename[: -len(".npy")]
                with zf.open(info) as fh:
                    version = np.lib.format.read_magic(fh)
                    if version == (1, 0):
                        _, _, dtype = np.lib.format.read_array_header_1_0(fh)
                    else:
                        _, _, dtype = np.lib.format.read_array_header_2_0(fh)
                    if dtype.hasobject:
                        try:
                            value = _ArrayUnpickler(fh).load()
                        except _TooManySteps:
                            raise InputError(
                                f"{path}: array {clip(name)}: its pickle takes more than "
                                f"{_MAX_PICKLE_STEPS:,} steps (a dict of arrays takes a few "
                                "per array); save it as plain arrays"
                            ) from None
                        values += _count_values(path, name, value, budget - values)
                        out[name] = value
                        continue
                with zf.open(info) as fh:
                    npy_header(path, fh, f"array {clip(name)}", info.file_size)
                with zf.open(info) as fh:
                    out[name] = np.lib.format.read_array(fh, allow_pickle=False)
    except InputError:
        raise
    except (
        zipfile.BadZipFile,
        OSError,
        ValueError,
        EOFError,
        TypeError,
        SyntaxError,
        NotImplementedError,
        pickle.UnpicklingError,
    ) as exc:
        raise InputError(f"{path}: not a readable .npz archive: {clip(str(exc))}") from None
    return out


#: Levels of lists, dicts and object arrays a pickled member may nest.
_MAX_NESTING = 8


def _count_values(path: Path, name: str, value: Any, budget: int) -> int:
    """Numbers a pickled member expands to, counted without building anything.

    Every reference counts (a list referred to twice is two lists' worth), as
    converting the member to arrays would copy it that often (each object is
    walked once). The walk stops as soon as the count passes ``budget``.

    Raises:
        InputError: More than ``budget`` numbers, or nested more than
            :data:`_MAX_NESTING` levels deep.
    """
    containers = (np.ndarray, list, tuple, dict)

    def size(v: Any) -> int:
        return int(v.size) if isinstance(v, np.ndarray) else len(v)

    def children(v: Any) -> Iterator[Any]:
        if isinstance(v, np.ndarray):
            return v.flat if v.dtype.hasobject else iter(())
        items = v.values() if isinstance(v, dict) else v
        # a flat list of numbers is not walked number by number (types are listed in C)
        if not any(issubclass(t, containers) for t in set(map(type, items))):
            return iter(())
        return iter(items)

    too_many = InputError(
        f"{path}: array {clip(name)} expands to more than {budget:,} numbers, more than "
        "candidates.max_count grasps need; raise candidates.max_count to read it"
    )
    # by id and depth: an object referred to again at the same depth is not walked again
    totals: dict[tuple[int, int], int] = {}

    def total(v: Any, depth: int) -> int:
        if not isinstance(v, containers):
            return 1
        if (id(v), depth) in totals:
            return totals[id(v), depth]
        if depth >= _MAX_NESTING:
            raise InputError(
                f"{path}: array {clip(name)} nests lists or dicts more than "
                f"{_MAX_NESTING} levels deep"
            )
        n = size(v)
        for child in children(v):
            if isinstance(child, containers):
                n += total(child, depth + 1)
                if n > budget:
                    raise too_many
        totals[id(v), depth] = n
        return n

    count = total(value, 0)
    if count > budget:
        raise too_many
    return count


def _segments(value: Any) -> dict[Any, np.ndarray]:
    """A per-segment dict (a 0-d object array holding one, or a plain array = segment -1)."""
    if isinstance(value, np.ndarray) and value.dtype.hasobject and value.ndim == 0:
        value = value.item()
    if isinstance(value, dict):
        return value
    return {-1: value}


def read_contact_graspnet(
    path: str | Path, *, max_count: int = DEFAULT_MAX_CANDIDATES
) -> ImportedGrasps:
    """Read Contact-GraspNet predictions (``pred_grasps_cam`` and friends).

    Segments are read in ascending order of their id; within a segment rows
    stay in file order.

    Args:
        path: The ``.npz`` file.
        max_count: Most grasps the file may hold (``candidates.max_count``);
            its arrays are sized before they are read.

    Returns:
        Gripper base poses (``base`` convention) in the camera frame with
        ``score``, ``width`` (``gripper_openings`` when present, else NaN),
        ``segment`` (the segment id) and ``source_id`` (the row inside its
        segment).

    Raises:
        InputError: Not an ``.npz`` with ``pred_grasps_cam``, inconsistent
            lengths, non-rigid poses.
    """
    path = Path(path)
    check_format(path, "contact_graspnet")
    arrays = _read_npz_members(path, max_count)
    if "pred_grasps_cam" not in arrays:
        raise InputError(
            f"{path}: not a Contact-GraspNet prediction file: no array 'pred_grasps_cam' "
            f"(arrays: {', '.join(arrays) or 'none'})"
        )
    grasps = _segments(arrays["pred_grasps_cam"])
    scores = _segments(arrays["scores"]) if "scores" in arrays else {}
    openings = _segments(arrays["gripper_openings"]) if "gripper_openings" in arrays else {}
    try:
        keys = sorted(grasps, key=lambda k: float(k))
    except (TypeError, ValueError):
        keys = sorted(grasps, key=str)
    parts: list[np.ndarray] = []
    cols: dict[str, list[Any]] = {"score": [], "width": [], "segment": [], "source_id": []}
    try:
        total = sum(int(np.size(v)) // 16 for v in grasps.values())
    except (TypeError, ValueError):  # ragged lists
        raise InputError(
            f"{path}: pred_grasps_cam must map segments to (M, 4, 4) arrays of poses"
        ) from None
    _check_count(path, total, max_count)
    for key in keys:
        what = f"pred_grasps_cam[{clip(key, 40)}]"
        value = grasps[key]
        raw = value if isinstance(value, np.ndarray) else np.asarray(value, dtype=object)
        if raw.size == 0:
            continue
        if raw.ndim not in (2, 3) or raw.shape[-2:] != (4, 4):
            raise InputError(
                f"{path}: {what} must be an (M, 4, 4) array of poses, got "
                f"{type(value).__name__} of shape {raw.shape}"
            )
        poses = check_poses(path, raw.reshape(-1, 4, 4), what)
        m = len(poses)
        parts.append(poses)
        score = scores.get(key)
        cols["score"].append(
            np.full(m, np.nan) if score is None else _vector(path, score, m, f"scores[{key}]")
        )
        width = openings.get(key)
        cols["width"].append(
            np.full(m, np.nan)
            if width is None
            else _vector(path, width, m, f"gripper_openings[{key}]")
        )
        try:
            seg = int(float(key))
        except (TypeError, ValueError, OverflowError):
            seg = keys.index(key)
        if abs(seg) >= 2**62:
            raise InputError(f"{path}: segment id {clip(key, 40)} is not an integer id")
        cols["segment"].append(np.full(m, seg, dtype=np.int64))
        cols["source_id"].append(np.arange(m, dtype=np.int64))
    if not parts:
        return ImportedGrasps(np.zeros((0, 4, 4)), "base", {})
    columns = {k: np.concatenate(v) for k, v in cols.items()}
    return ImportedGrasps(np.concatenate(parts), "base", columns)


# ----------------------------------------------------------------- GraspNet

GRASPNET_ROW = 17


def read_graspnet(path: str | Path, *, max_count: int = DEFAULT_MAX_CANDIDATES) -> ImportedGrasps:
    """Read GraspNet-1Billion / AnyGrasp grasp rows (``GraspGroup`` arrays).

    Args:
        path: The ``.npy`` (or ``.npz``) file.
        max_count: Most grasps the file may hold (``candidates.max_count``),
            checked from the array's header before it is read.

    Returns:
        Grasp-centre poses (``center`` convention) with ``score``, ``width``
        [m], ``object_id`` and ``source_id`` (row in the file); ``depth`` [m].

    Raises:
        InputError: Not a (N, 17) real array, non-rigid rotation, bad values.
    """
    path = Path(path)
    check_format(path, "graspnet")
    kind = getattr(sniff(path), "kind", None)  # the suffix when the start says nothing
    if kind == "zip" or (kind is None and path.suffix.lower() == ".npz"):
        arrays = _read_npz_members(path, max_count)
        names: list[str] = [k for k in ("grasp_group_array", "grasps", "preds") if k in arrays]
        if not names and len(arrays) == 1:
            names = list(arrays)
        if not names:
            raise InputError(
                f"{path}: expected one array of GraspNet rows (N, {GRASPNET_ROW}) or "
                f"'grasp_group_array'; arrays: {', '.join(arrays) or 'none'}"
            )
        rows = arrays[names[0]]
    else:
        rows = _read_graspnet_npy(path, max_count)
    rows = np.asarray(rows)
    _check_graspnet_shape(path, rows.shape, rows.dtype)
    _check_count(path, len(rows), max_count)
    rows = rows.astype(float)
    bad = np.flatnonzero(~np.isfinite(rows).all(axis=1))
    if bad.size:
        raise InputError(f"{path}: row {int(bad[0])} (0-based) has non-finite values")
    bad = np.flatnonzero(np.abs(rows[:, 16]) >= 2.0**53)
    if bad.size:
        raise InputError(
            f"{path}: row {int(bad[0])} (0-based): object_id {rows[bad[0], 16]:g} is not an "
            "integer id"
        )
    n = len(rows)
    poses = np.zeros((n, 4, 4))
    poses[:, :3, :3] = rows[:, 4:13].reshape(n, 3, 3)
    poses[:, :3, 3] = rows[:, 13:16]
    poses[:, 3, 3] = 1.0
    poses = check_poses(path, poses, "rotation/translation")
    columns = {
        "score": rows[:, 0].copy(),
        "width": rows[:, 1].copy(),
        "object_id": np.rint(rows[:, 16]).astype(np.int64),
        "source_id": np.arange(n, dtype=np.int64),
    }
    return ImportedGrasps(poses, "center", columns, depth=rows[:, 3].copy())


def _check_graspnet_shape(path: Path, shape: tuple[int, ...], dtype: np.dtype[Any]) -> None:
    if len(shape) != 2 or shape[1] != GRASPNET_ROW or dtype.kind not in "fiu":
        raise InputError(
            f"{path}: expected GraspNet rows (N, {GRASPNET_ROW}) = [score, width, height, "
            f"depth, R (9), t (3), object_id], got shape {shape} dtype {dtype}"
        )


def _read_graspnet_npy(path: Path, max_count: int) -> np.ndarray:
    """The rows of a ``.npy`` file, its header checked before the data is read."""
    from gcm_pipeline.rundir.arrays import npy_header

    try:
        with path.open("rb") as fh:
            shape, dtype = npy_header(path, fh, "the array", path.stat().st_size)
            _check_graspnet_shape(path, shape, dtype)
            _check_count(path, shape[0], max_count)
            fh.seek(0)
            return np.lib.format.read_array(fh, allow_pickle=False)
    except OSError as exc:
        raise InputError(f"{path}: cannot read: {exc.strerror or exc}") from None
    except ValueError as exc:
        raise InputError(f"{path}: not a readable .npy array: {clip(str(exc))}") from None


READERS = {
    "graspgen": read_graspgen,
    "contact_graspnet": read_contact_graspnet,
    "graspnet": read_graspnet,
}
