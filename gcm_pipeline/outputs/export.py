"""Exporters of a finished run: MoveIt grasps (YAML), Parquet, NPZ.

========== ===================================================================
format     file
========== ===================================================================
``moveit`` a YAML list of ``moveit_msgs/Grasp`` messages (ROS 2 field names:
           ``header.stamp.{sec, nanosec}``), one per reachable grasp, best
           first; readable with any YAML parser, no ROS needed
``parquet`` the grasp table as in ``grasps.csv`` (same rows, same order, same
           column names; ``q`` one list column instead of ``q1 .. qN``), for
           pandas / polars / DuckDB; a cell empty in ``grasps.csv`` is null
           (never NaN), so their ``count``/``avg``/``min``/``max`` agree
``npz``    the same columns as arrays, ``q`` (N, nq), plus ``pose`` (N, 4, 4)
           world poses of the grasp frame
========== ===================================================================

``moveit_msgs/Grasp`` fields (from the message definition in moveit_msgs):
``id``; ``pre_grasp_posture`` / ``grasp_posture`` (``trajectory_msgs/
JointTrajectory`` of the hand's finger joints); ``grasp_pose``
(``geometry_msgs/PoseStamped``); ``grasp_quality``; ``pre_grasp_approach``,
``post_grasp_retreat``, ``post_place_retreat`` (``GripperTranslation``:
``direction`` as a ``Vector3Stamped``, ``desired_distance``,
``min_distance``); ``max_contact_force``; ``allowed_touch_objects``.

Here ``grasp_pose`` is the pose of the robot spec's grasp frame (the Panda's
``panda_hand_tcp``) in the robot's root frame (``header.frame_id``, e.g.
``panda_link0``): the pose the pipeline checked. MoveIt's pick pipeline reads
``grasp_pose`` as the pose of the end effector's parent link; configure the
end effector on the grasp frame, or offset the poses. ``grasp_quality`` is
the run's ranking metric as the ranking counted it (``margin``: ``inf``, no
unreachable point in reach, as the largest finite margin), so it is finite
and never increases down the list: MoveIt's pick tries grasps in decreasing
``grasp_quality``; ``pre_grasp_approach`` follows the config's
``approach`` (along +z of the grasp frame, ``min_distance`` = the checked
distance); ``post_grasp_retreat`` follows the config's ``retreat`` when the
run has one, else the approach reversed. Finger postures use the gripper
registry's finger joints when the robot's spec locks them (open as locked;
closed to half the grasp's ``width`` per finger when known, else 0).
"""

from __future__ import annotations

import csv
import math
import os
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any, NamedTuple, Protocol

import numpy as np
import yaml
from scipy.spatial.transform import Rotation

from gcm_pipeline.errors import InputError, OutputError, choice_error
from gcm_pipeline.geometry.dualquat import dq_to_matrix, dq_to_pos_quat
from gcm_pipeline.ranking.metrics import METRIC_COLUMNS
from gcm_pipeline.rundir.grasps_csv import CSV_COLUMNS, read_grasps_csv
from gcm_pipeline.rundir.run import objects_hint
from gcm_pipeline.rundir.transaction import atomic_file, read_marker
from gcm_pipeline.table import GraspTable

__all__ = ["EXPORT_FORMATS", "ExportResult", "MoveItOptions", "RunConfig", "export_run"]

#: Export formats and their default file names (inside the run directory).
EXPORT_FORMATS = {"moveit": "grasps_moveit.yaml", "parquet": "grasps.parquet", "npz": "grasps.npz"}


@dataclass(frozen=True, eq=False)
class MoveItOptions:
    """What a MoveIt export takes from the run's config and robot spec.

    Attributes:
        root_frame: The robot's root frame (``header.frame_id`` of the poses).
        grasp_frame: The spec's grasp frame.
        locked_joints: The spec's locked joints and their values [rad or m].
        base_pose: The robot's base in the world (4, 4) [m].
        metric: The run's ranking metric (``grasp_quality``).
        approach_distance: The checked approach distance [m] (0: none).
        retreat_direction: The retreat's direction (None: the approach reversed).
        retreat_frame: ``world`` or ``grasp``: the frame of ``retreat_direction``.
        retreat_distance: The retreat's distance [m].
        finger_joints: The hand's finger joints among ``locked_joints`` (the
            postures' joints; none: empty postures).
        hand_frame: The hand's base link (the postures' frame; None: the grasp frame).
    """

    root_frame: str
    grasp_frame: str
    locked_joints: Mapping[str, float]
    base_pose: np.ndarray
    metric: str
    approach_distance: float = 0.0
    retreat_direction: tuple[float, float, float] | None = None
    retreat_frame: str = "world"
    retreat_distance: float = 0.0
    finger_joints: tuple[str, ...] = ()
    hand_frame: str | None = None


class RunConfig(Protocol):
    """A run's ``config.yaml`` as an export takes it (:mod:`gcm_pipeline.pipeline` reads it)."""

    #: The run's ranking metric.
    ranking_metric: str

    def moveit(self) -> MoveItOptions:
        """The MoveIt export's options (reads the run's robot spec)."""
        ...


class ExportResult(NamedTuple):
    """What :func:`export_run` wrote.

    Attributes:
        path: The file written.
        rows: Number of grasps in it.
    """

    path: Path
    rows: int


def export_run(
    run_dir: str | os.PathLike[str],
    format: str,
    *,
    read_config: Callable[[Path], RunConfig],
    top: int | None = None,
    out: str | os.PathLike[str] | None = None,
) -> ExportResult:
    """Export a run directory's grasps.

    Args:
        run_dir: A run directory written by ``gcm run``.
        format: ``moveit``, ``parquet`` or ``npz``.
        read_config: Reads the run's ``config.yaml`` (its path), e.g.
            :func:`gcm_pipeline.pipeline.outputs.read_run_config`.
        top: Keep only the ``top`` best-ranked reachable grasps (moveit
            always exports ranked grasps only; default all of them).
        out: The file to write (default: ``RUN_DIR/`` + the format's name in
            :data:`EXPORT_FORMATS`). Written atomically; a symbolic link is
            kept and the file it names is replaced.

    Returns:
        The file and the number of grasps written.

    Raises:
        InputError: Not a run directory, unknown format, ``top < 1``, ``out``
            naming one of the run's own files, or no reachable grasp to
            export (after an empty, valid file is written).
        ConfigError: The run's ``config.yaml`` is not a valid config.
        OutputError: The file cannot be written, or ``out`` is a directory, a
            device or a pipe.
    """
    if format not in EXPORT_FORMATS:
        raise choice_error(InputError, "export format", format, EXPORT_FORMATS)
    if top is not None and top < 1:
        raise InputError(f"--top must be >= 1, got {top}")
    run = Path(run_dir)
    if not (run / "grasps.csv").is_file() or not (run / "config.yaml").is_file():
        hint = objects_hint(run)
        raise InputError(f"not a run directory: {run} (needs grasps.csv and config.yaml){hint}")
    if out is not None and os.fspath(out).endswith(("/", os.sep)):
        raise OutputError(f"cannot write {os.fspath(out)}: a file name, not a folder, is needed")
    path = _output_file(Path(out) if out is not None else run / EXPORT_FORMATS[format])
    _check_not_the_run(run, path)
    grasps = read_grasps_csv(run / "grasps.csv")  # file order: ranked first
    # the exact x..qz of the file (the dq column rebuilt from them may differ by an ulp)
    grasps = grasps.with_columns(pose7=_csv_pose(run / "grasps.csv", len(grasps)))
    config = read_config(run / "config.yaml")
    ranked = np.asarray(grasps["rank"]) > 0 if "rank" in grasps else np.zeros(len(grasps), bool)
    if format == "moveit":  # from every ranked row, before --top keeps some
        grasps = grasps.with_columns(
            grasp_quality=_grasp_quality(grasps, config.ranking_metric, run / "grasps.csv")
        )
    if format == "moveit" or top is not None:
        rows = np.flatnonzero(ranked)
        if top is not None:
            rows = rows[:top]
        grasps = grasps.take(rows)
    writers: dict[str, Callable[[GraspTable, Path], None]] = {
        "moveit": lambda g, p: _write_moveit(g, config.moveit(), p),
        "parquet": _write_parquet,
        "npz": _write_npz,
    }
    _atomic(path, lambda tmp: writers[format](grasps, tmp))
    if (format == "moveit" or top is not None) and len(grasps) == 0:
        raise InputError(
            f"{run}: no reachable grasp to export; wrote an empty {format} file {path}"
        )
    return ExportResult(path, len(grasps))


_POSE7 = ("x", "y", "z", "qw", "qx", "qy", "qz")


def _csv_pose(path: Path, n: int) -> np.ndarray:
    """The ``x, y, z, qw, qx, qy, qz`` columns of ``grasps.csv`` as written (N, 7)."""
    # read as read_grasps_csv reads it (which has checked the file): BOM and blank lines
    with path.open(newline="", encoding="utf-8-sig") as fh:
        rows = [row for row in csv.reader(fh) if any(cell.strip() for cell in row)]
    cols = [rows[0].index(c) for c in _POSE7]
    return np.array([[float(row[j]) for j in cols] for row in rows[1:]]).reshape(n, 7)


#: Files of a run directory an export never replaces (every file ``gcm run`` writes).
_RUN_OWN_FILES = frozenset(
    ("grasps.csv", "summary.json", "manifold.npz", "config.yaml", "configurations.npz")
    + ("solutions.npz", ".gcm.json", "scene.html")
)

#: Files of a study directory an export never replaces (and ``placements/*``).
_STUDY_OWN_FILES = frozenset(
    ("study.json", "placements.csv", "reachability.npz", "summary.json", ".gcm.json")
    + (".study.lock",)
)


def _check_not_the_run(run: Path, path: Path) -> None:
    """Refuse an export file that would replace a file ``gcm run`` or ``gcm study`` wrote.

    The file (symbolic links resolved) must not be one of the run's own files
    (its ``.png`` plots included), nor one of another run's or study's
    directory (a folder with this project's marker) or a study's placement.
    """
    target = path.resolve()
    folder = target.parent
    kind = (read_marker(folder) or {}).get("kind")
    if folder == run.resolve():
        kind = "run"
    own = {"run": _RUN_OWN_FILES, "study": _STUDY_OWN_FILES}.get(str(kind))
    if own is not None and (target.name in own or target.suffix.lower() == ".png"):
        whose = "the run's own" if folder == run.resolve() else f"the {kind} directory's"
        raise InputError(
            f"--out {path} would overwrite {whose} {target.name} ({folder}); choose another file"
        )
    if folder.name == "placements" and (read_marker(folder.parent) or {}).get("kind") == "study":
        raise InputError(
            f"--out {path} would overwrite a placement of the study {folder.parent}; "
            "choose another file"
        )


def _output_file(path: Path) -> Path:
    """The file an export replaces: ``path``, or the file a symbolic link there names.

    Raises:
        OutputError: ``path`` (or the link's target) exists and is no regular file
            (a directory, ``/dev/null``, a pipe): a rename would replace it.
    """
    try:
        target = path.resolve(strict=False) if path.is_symlink() else path
        exists, regular = target.exists(), target.is_file()
    except (OSError, ValueError, RuntimeError) as exc:  # RuntimeError: a symbolic link loop
        raise OutputError(f"cannot write {path}: {exc}") from None
    if exists and not regular:
        what = "a directory" if target.is_dir() else "not a regular file"
        raise OutputError(f"cannot write {path}: it is {what}; give a file name")
    return target


def _atomic(path: Path, write: Callable[[Path], None]) -> None:
    """Write through ``write(tmp)`` into a sibling temporary file, then rename."""
    parent = path.parent
    if not parent.is_dir():
        what = "is not a directory" if parent.exists() else "does not exist"
        raise OutputError(f"cannot write {path}: {parent} {what}")
    try:
        with atomic_file(path) as tmp:
            write(tmp)
    except OSError as exc:
        raise OutputError(f"cannot write {path}: {exc}") from None


# ------------------------------------------------------------------ columns


def _flat_columns(g: GraspTable) -> dict[str, np.ndarray]:
    """The grasps.csv columns (names and values) of a table, ``q`` kept 2-D."""
    n = len(g)
    if "pose7" in g:
        pos, quat = g["pose7"][:, :3], g["pose7"][:, 3:]
    else:
        pos, quat = dq_to_pos_quat(np.asarray(g["dq"], dtype=float).reshape(n, 8))
        quat = np.where(quat[:, :1] < 0, -quat, quat)
    cols: dict[str, np.ndarray] = {}
    for name in CSV_COLUMNS:
        if name in ("v1", "v2", "v3") and "vertices" in g:
            cols[name] = np.asarray(g["vertices"])[:, int(name[1]) - 1]
        elif name in ("w1", "w2", "w3") and "weights" in g:
            cols[name] = np.asarray(g["weights"])[:, int(name[1]) - 1]
        elif name in ("x", "y", "z"):
            cols[name] = pos[:, "xyz".index(name)]
        elif name in ("qw", "qx", "qy", "qz"):
            cols[name] = quat[:, ("qw", "qx", "qy", "qz").index(name)]
        elif name in g:
            cols[name] = np.asarray(g[name])
    if "q" in g:
        q = np.asarray(g["q"], dtype=float)
        cols["q"] = q.reshape(n, q.shape[-1] if q.ndim == 2 else -1)
    for name in g.columns:
        col = np.asarray(g[name])
        if (
            name not in cols
            and name not in ("dq", "vertices", "weights", "pose7")
            and col.ndim == 1
        ):
            cols[name] = col
    return cols


def _arrow_column(col: np.ndarray) -> Any:
    """One column as Arrow, a missing value (NaN, empty text) as null.

    grasps.csv writes a missing value as an empty cell, which DuckDB, polars
    and pandas read as null; a NaN in Parquet would be a value that ``avg``
    and ``count`` take in.
    """
    import pyarrow as pa

    if col.ndim == 2:  # q: a list per row; null when the row has no joint value
        values = np.asarray(col, dtype=float)
        missing = np.isnan(values)
        flat = pa.array(values.reshape(-1), type=pa.float64(), mask=missing.reshape(-1))
        offsets = pa.array(np.arange(0, values.size + 1, max(values.shape[1], 1), dtype=np.int32))
        if values.shape[1] == 0:
            offsets = pa.array(np.zeros(len(values) + 1, dtype=np.int32))
        rows_missing = pa.array(missing.all(axis=1) & (values.shape[1] > 0))
        return pa.ListArray.from_arrays(offsets, flat, mask=rows_missing)
    if col.dtype.kind in "USO":
        text = col.astype(str)
        return pa.array(text.tolist(), type=pa.string(), mask=text == "")
    if col.dtype.kind == "f":
        return pa.array(col, mask=np.isnan(col))
    return pa.array(col)


def _write_parquet(g: GraspTable, path: Path) -> None:
    import pyarrow as pa
    import pyarrow.parquet as pq

    cols = _flat_columns(g)
    table = pa.Table.from_arrays([_arrow_column(c) for c in cols.values()], names=list(cols))
    pq.write_table(table, path)


def _write_npz(g: GraspTable, path: Path) -> None:
    cols = _flat_columns(g)
    arrays: dict[str, Any] = {
        k: (v.astype(str) if v.dtype.kind in "USO" else v) for k, v in cols.items()
    }
    pose = np.zeros((len(g), 4, 4))
    pose[:, :3, :3] = (
        Rotation.from_quat(np.c_[cols["qx"], cols["qy"], cols["qz"], cols["qw"]]).as_matrix()
        if len(g)
        else 0.0
    )
    pose[:, :3, 3] = np.c_[cols["x"], cols["y"], cols["z"]]
    pose[:, 3, 3] = 1.0
    arrays["pose"] = pose
    with path.open("wb") as fh:
        np.savez(fh, **arrays)


# ------------------------------------------------------------------ MoveIt


def _grasp_quality(g: GraspTable, metric: str, path: Path) -> np.ndarray:
    """``grasp_quality`` per row: the ranking metric as the ranking counted it.

    ``inf`` (a ``margin`` with no unreachable point in reach) is the largest
    finite value of the ranked rows, as :func:`gcm_pipeline.ranking.rank.rank`
    counts it (1.0 when none is finite), so the value is finite and never
    increases with the rank: MoveIt's pick sorts its grasps by it, best first.

    Raises:
        InputError: The metric's column is missing, or a ranked row's value
            is not finite or is larger than the row ranked above it (a
            ``grasps.csv`` whose ranks and values disagree).
    """
    n = len(g)
    rank = np.asarray(g["rank"], dtype=np.int64) if "rank" in g else np.zeros(n, np.int64)
    name = METRIC_COLUMNS.get(metric, metric)
    if not (rank > 0).any():
        return np.full(n, np.nan)
    if name not in g:
        raise InputError(f"{path}: no column {name!r} of the run's ranking metric {metric!r}")
    value = np.array(g[name], dtype=float)
    ranked = np.flatnonzero(rank > 0)
    ranked = ranked[np.argsort(rank[ranked], kind="stable")]
    finite = value[ranked][np.isfinite(value[ranked])]
    value[np.isposinf(value)] = float(finite.max()) if finite.size else 1.0
    v = value[ranked]
    bad = np.flatnonzero(~np.isfinite(v) | (np.diff(v, prepend=v[0]) > 0))
    if bad.size:
        i = int(bad[0])
        raise InputError(
            f"{path}: rank {int(rank[ranked[i]])} has {name} {v[i]!r}, "
            + ("not a number" if not np.isfinite(v[i]) else f"more than rank above's {v[i - 1]!r}")
            + "; the file's ranks and values disagree"
        )
    return value


def _stamp() -> dict[str, int]:
    return {"sec": 0, "nanosec": 0}


def _header(frame: str) -> dict[str, Any]:
    return {"stamp": _stamp(), "frame_id": frame}


def _translation(frame: str, vector: np.ndarray, distance: float, min_distance: float) -> dict:
    x, y, z = (float(v) for v in vector)
    return {
        "direction": {"header": _header(frame), "vector": {"x": x, "y": y, "z": z}},
        "desired_distance": float(distance),
        "min_distance": float(min_distance),
    }


def _posture(frame: str, joints: list[str], positions: list[float], t: float) -> dict:
    points = []
    if joints:
        sec = int(math.floor(t))
        points = [
            {
                "positions": [float(p) for p in positions],
                "velocities": [],
                "accelerations": [],
                "effort": [],
                "time_from_start": {"sec": sec, "nanosec": int(round((t - sec) * 1e9))},
            }
        ]
    return {"header": _header(frame), "joint_names": list(joints), "points": points}


def _write_moveit(g: GraspTable, options: MoveItOptions, path: Path) -> None:
    root, tool = options.root_frame, options.grasp_frame
    locked = dict(options.locked_joints)
    base = options.base_pose
    n = len(g)
    world = dq_to_matrix(np.asarray(g["dq"], dtype=float).reshape(n, 8))
    in_base = np.linalg.inv(base) @ world
    pos = in_base[:, :3, 3]
    quat = Rotation.from_matrix(in_base[:, :3, :3]).as_quat() if n else np.zeros((0, 4))
    metric = options.metric
    quality = np.asarray(g["grasp_quality"], dtype=float)
    width = np.asarray(g["width"], dtype=float) if "width" in g else np.full(n, np.nan)
    joints = list(options.finger_joints)
    open_pos = [float(locked[j]) for j in joints]
    hand_frame = options.hand_frame or tool
    d_app = options.approach_distance
    if options.retreat_direction is not None:
        direction = np.asarray(options.retreat_direction, dtype=float)
        direction = direction / np.linalg.norm(direction)
        if options.retreat_frame == "world":
            retreat_frame, retreat_dir = root, np.linalg.inv(base)[:3, :3] @ direction
        else:
            retreat_frame, retreat_dir = tool, direction
        d_ret = float(options.retreat_distance)
    else:  # the approach reversed
        retreat_frame, retreat_dir, d_ret = tool, np.array([0.0, 0.0, -1.0]), d_app
    rank = np.asarray(g["rank"]) if "rank" in g else np.arange(1, n + 1)
    grasps = []
    for i in range(n):
        closed = [0.5 * width[i] if np.isfinite(width[i]) else 0.0] * len(joints)
        x, y, z = (float(v) for v in pos[i])
        qx, qy, qz, qw = (float(v) for v in quat[i])
        grasps.append(
            {
                "id": f"rank_{int(rank[i])}",
                "pre_grasp_posture": _posture(hand_frame, joints, open_pos, 0.0),
                "grasp_posture": _posture(hand_frame, joints, closed, 1.0),
                "grasp_pose": {
                    "header": _header(root),
                    "pose": {
                        "position": {"x": x, "y": y, "z": z},
                        "orientation": {"x": qx, "y": qy, "z": qz, "w": qw},
                    },
                },
                "grasp_quality": float(quality[i]),
                "pre_grasp_approach": _translation(tool, np.array([0, 0, 1.0]), d_app, d_app),
                "post_grasp_retreat": _translation(retreat_frame, retreat_dir, d_ret, d_ret),
                "post_place_retreat": _translation("", np.zeros(3), 0.0, 0.0),
                "max_contact_force": 0.0,
                "allowed_touch_objects": [],
            }
        )
    head = (
        f"# moveit_msgs/Grasp list (ROS 2 field names), {n} grasps, best first.\n"
        f"# grasp_pose: the grasp frame {tool!r} in the robot root frame {root!r};\n"
        f"# grasp_quality: the ranking metric {metric!r} (inf: the largest finite value).\n"
    )
    text = yaml.safe_dump(grasps, sort_keys=False, default_flow_style=None, width=100)
    path.write_text(head + text, encoding="utf-8")
