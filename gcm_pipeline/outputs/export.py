"""Exporters of a finished run: MoveIt grasps (YAML), ROS 2 bag (MCAP), Parquet, NPZ.

========== ===================================================================
format     file
========== ===================================================================
``moveit`` a YAML list of ``moveit_msgs/Grasp`` messages (ROS 2 field names:
           ``header.stamp.{sec, nanosec}``), one per reachable grasp, best
           first; readable with any YAML parser, no ROS needed; with
           ``trajectory=True`` each also has a ``trajectory`` entry, the
           arm's ``trajectory_msgs/JointTrajectory`` approach -> grasp -> retreat
``mcap``   a ROS 2 bag in one MCAP file (:mod:`~gcm_pipeline.outputs.export_mcap`):
           ``/grasps`` (``moveit_msgs/Grasp``), ``/grasp_trajectories``
           (``JointTrajectory``), ``/scene_markers``, ``/tf_static``
``parquet`` the grasp table as in ``grasps.csv`` (same rows, same order, same
           column names; ``q`` one list column instead of ``q1 .. qN``), for
           pandas / polars / DuckDB; a cell empty in ``grasps.csv`` is null
           (never NaN), so their ``count``/``avg``/``min``/``max`` agree
``npz``    the same columns as arrays, ``q`` (N, nq), plus ``pose`` (N, 4, 4)
           world poses of the grasp frame
========== ===================================================================

The messages' mappings are built by :mod:`~gcm_pipeline.outputs.moveit_grasps`.
In the YAML, ``grasp_pose`` is the pose of the robot spec's grasp frame (the Panda's
``panda_hand_tcp``) in the robot's root frame (``header.frame_id``, e.g.
``panda_link0``): the pose the pipeline checked; in the bag it is in ``world``
(``/tf_static`` places the root frame). MoveIt's pick pipeline reads
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
closed to half the grasp's ``width`` per finger when known, else 0). The
arm trajectories come from ``configurations.npz`` (``q_pregrasp``, ``q``,
``q_retreat``), with the robot's joint names.
"""

from __future__ import annotations

import os
from collections.abc import Callable
from datetime import datetime
from pathlib import Path
from typing import TYPE_CHECKING, Any, NamedTuple, Protocol

import numpy as np
import yaml
from scipy.spatial.transform import Rotation

from gcm_pipeline.errors import InputError, OutputError, choice_error
from gcm_pipeline.geometry.dualquat import dq_to_pos_quat
from gcm_pipeline.outputs import export_mcap
from gcm_pipeline.outputs.moveit_grasps import MoveItOptions, arm_trajectory, grasp_messages
from gcm_pipeline.ranking.metrics import METRIC_COLUMNS
from gcm_pipeline.rundir.arrays import read_npz
from gcm_pipeline.rundir.grasps_csv import CSV_COLUMNS, read_grasps_csv_pose
from gcm_pipeline.rundir.run import objects_hint
from gcm_pipeline.rundir.transaction import atomic_file, read_marker
from gcm_pipeline.table import GraspTable

if TYPE_CHECKING:
    from gcm_pipeline.outputs.scene import SceneOptions

__all__ = ["EXPORT_FORMATS", "ExportResult", "MoveItOptions", "RunConfig", "export_run"]

#: Export formats and their default file names (inside the run directory).
EXPORT_FORMATS = {
    "moveit": "grasps_moveit.yaml",
    "mcap": "grasps.mcap",
    "parquet": "grasps.parquet",
    "npz": "grasps.npz",
}

#: Formats of the reachable grasps only, best first (``--top`` or not).
_RANKED_ONLY = ("moveit", "mcap")


class RunConfig(Protocol):
    """A run's ``config.yaml`` as an export takes it (:mod:`gcm_pipeline.pipeline` reads it)."""

    @property
    def ranking_metric(self) -> str:
        """The run's ranking metric."""
        ...

    def moveit(self) -> MoveItOptions:
        """The MoveIt export's options (reads the run's robot spec)."""
        ...

    def scene(self) -> SceneOptions:
        """The run's scene: its object, table and obstacles (the bag's markers)."""
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
    trajectory: bool = False,
) -> ExportResult:
    """Export a run directory's grasps.

    Args:
        run_dir: A run directory written by ``gcm run``.
        format: ``moveit``, ``mcap``, ``parquet`` or ``npz``.
        read_config: Reads the run's ``config.yaml`` (its path), e.g.
            :func:`gcm_pipeline.pipeline.outputs.read_run_config`.
        top: Keep only the ``top`` best-ranked reachable grasps (moveit and
            mcap always export ranked grasps only; default all of them).
        out: The file to write (default: ``RUN_DIR/`` + the format's name in
            :data:`EXPORT_FORMATS`). Written atomically; a symbolic link is
            kept and the file it names is replaced.
        trajectory: ``moveit``: give each grasp a ``trajectory`` entry, the
            arm's joint trajectory approach -> grasp -> retreat.

    Returns:
        The file and the number of grasps written.

    Raises:
        InputError: Not a run directory, unknown format, ``top < 1``, ``out``
            naming one of the run's own files, ``trajectory`` with another
            format than ``moveit``, a missing or damaged ``configurations.npz``
            (``mcap``, ``trajectory``), rosbags not installed (``mcap``), or no
            reachable grasp to export (after an empty, valid file is written).
        ConfigError: The run's ``config.yaml`` is not a valid config.
        OutputError: The file cannot be written, or ``out`` is a directory, a
            device or a pipe.
    """
    if format not in EXPORT_FORMATS:
        raise choice_error(InputError, "export format", format, EXPORT_FORMATS)
    if top is not None and top < 1:
        raise InputError(f"--top must be >= 1, got {top}")
    if trajectory and format != "moveit":
        raise InputError(f"--trajectory is for --format moveit (the {format} export has none)")
    run = Path(run_dir)
    if not (run / "grasps.csv").is_file() or not (run / "config.yaml").is_file():
        hint = objects_hint(run)
        raise InputError(f"not a run directory: {run} (needs grasps.csv and config.yaml){hint}")
    if out is not None and os.fspath(out).endswith(("/", os.sep)):
        raise OutputError(f"cannot write {os.fspath(out)}: a file name, not a folder, is needed")
    path = _output_file(Path(out) if out is not None else run / EXPORT_FORMATS[format])
    _check_not_the_run(run, path)
    everything, pose7 = read_grasps_csv_pose(run / "grasps.csv")  # file order: ranked first
    # the exact x..qz of the file (the dq column rebuilt from them may differ by an ulp)
    grasps = everything.with_columns(pose7=pose7)
    config = read_config(run / "config.yaml")
    n = len(grasps)
    ranked = np.asarray(grasps["rank"]) > 0 if "rank" in grasps else np.zeros(n, bool)
    if format in _RANKED_ONLY:  # from every ranked row, before --top keeps some
        grasps = grasps.with_columns(
            grasp_quality=_grasp_quality(grasps, config.ranking_metric, run / "grasps.csv")
        )
    rows = np.arange(n)
    if format in _RANKED_ONLY or top is not None:
        rows = np.flatnonzero(ranked)[:top]
        grasps = grasps.take(rows)
    writers: dict[str, Callable[[GraspTable, Path], None]] = {
        "parquet": _write_parquet,
        "npz": _write_npz,
    }
    if format in _RANKED_ONLY:
        moveit = config.moveit()
        conf: dict[str, np.ndarray] | None = None
        if format == "mcap" or trajectory:
            conf = _configurations(run / "configurations.npz", n, moveit.joint_names, rows)
        if format == "mcap":
            export_mcap.check_rosbags()
        writers["moveit"] = lambda g, p: _write_moveit(g, moveit, p, conf)
        writers["mcap"] = lambda g, p: _write_mcap(
            g, everything, conf or {}, moveit, config, p, run, path
        )
    _atomic(path, lambda tmp: writers[format](grasps, tmp))
    if (format in _RANKED_ONLY or top is not None) and len(grasps) == 0:
        raise InputError(
            f"{run}: no reachable grasp to export; wrote an empty {format} file {path}"
        )
    return ExportResult(path, len(grasps))


#: The configurations an arm trajectory takes from ``configurations.npz``.
_TRAJECTORY_COLUMNS = ("q_pregrasp", "q", "q_retreat")


def _configurations(
    path: Path, n: int, joint_names: tuple[str, ...], rows: np.ndarray
) -> dict[str, np.ndarray]:
    """``q_pregrasp``, ``q``, ``q_retreat`` of ``configurations.npz`` at ``rows`` (K, nq).

    Raises:
        InputError: The file is missing, damaged, or its arrays are not
            (grasps.csv rows, the robot's joints).
    """
    if not path.is_file():
        raise InputError(
            f"{path.parent}: no configurations.npz (the joint solutions the trajectories "
            "need); run gcm run again",
            path=path,
        )
    nq = len(joint_names)
    arrays = read_npz(
        path,
        max_bytes=4 * 8 * max(n, 1) * max(nq, 1) + 4096,
        keep=lambda name, shape, dtype: name in _TRAJECTORY_COLUMNS,
    )
    for name in _TRAJECTORY_COLUMNS:
        a = arrays.get(name)
        if a is None or a.shape != (n, nq) or a.dtype.kind != "f":
            what = "missing" if a is None else f"{a.dtype} {a.shape}"
            raise InputError(
                f"{path}: array {name!r} is {what}; expected float ({n}, {nq}): one row per "
                f"row of grasps.csv, one column per joint of the robot",
                path=path,
            )
    return {name: arrays[name][rows] for name in _TRAJECTORY_COLUMNS}


def _start_ns(run: Path) -> int:
    """The run's creation time (its marker) [ns since the epoch]; 0 when unknown."""
    created = (read_marker(run) or {}).get("created")
    try:
        when = datetime.fromisoformat(str(created).replace("Z", "+00:00"))
    except ValueError:
        return 0
    return int(when.timestamp()) * 1_000_000_000 if when.tzinfo is not None else 0


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


def _write_moveit(
    g: GraspTable,
    options: MoveItOptions,
    path: Path,
    configurations: dict[str, np.ndarray] | None,
) -> None:
    """The YAML list of Grasp mappings; with ``configurations``, each with a ``trajectory``."""
    grasps = grasp_messages(g, options)
    if configurations is not None:
        for i, grasp in enumerate(grasps):
            q = [configurations[c][i] for c in _TRAJECTORY_COLUMNS]
            grasp["trajectory"] = arm_trajectory(options, *q)
    root, tool, metric = options.root_frame, options.grasp_frame, options.metric
    head = (
        f"# moveit_msgs/Grasp list (ROS 2 field names), {len(g)} grasps, best first.\n"
        f"# grasp_pose: the grasp frame {tool!r} in the robot root frame {root!r};\n"
        f"# grasp_quality: the ranking metric {metric!r} (inf: the largest finite value).\n"
    )
    if configurations is not None:
        head += (
            "# trajectory: the arm's trajectory_msgs/JointTrajectory (not a Grasp field):\n"
            "# pre-grasp (0 s), grasp (1 s), retreat (2 s), nominal times.\n"
        )
    text = yaml.safe_dump(grasps, sort_keys=False, default_flow_style=None, width=100)
    path.write_text(head + text, encoding="utf-8")


def _write_mcap(
    g: GraspTable,
    everything: GraspTable,
    configurations: dict[str, np.ndarray],
    options: MoveItOptions,
    config: RunConfig,
    path: Path,
    run: Path,
    target: Path,
) -> None:
    """The ROS 2 bag (:func:`gcm_pipeline.outputs.export_mcap.write_mcap`) into ``path``.

    ``target``: the file ``path`` becomes (the bag's metadata names it).
    """
    scene = config.scene()
    export_mcap.write_mcap(
        path,
        g,
        everything,
        configurations,
        options,
        (scene.object, scene.table, scene.obstacles),
        _start_ns(run),
        target.name,
    )
