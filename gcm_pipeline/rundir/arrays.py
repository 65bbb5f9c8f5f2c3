"""The run directory's NumPy files, written and read back (checked before loading).

- ``manifold.npz``: ``vertex_ids``, ``chart``, ``triangles``, ``dropped``,
  ``dropped_reason``, ``projection``, ``triangulator`` and the chart ``frame``.
- ``configurations.npz``: the joint configurations [rad], one (N, nq) array
  per table column, rows in ``grasps.csv`` order: ``q`` (the solution),
  ``q_pregrasp`` (end of the approach), ``q_retreat`` (end of the retreat)
  and ``q_rejected`` (for unreachable grasps, the IK solution that collided
  or whose approach or retreat failed); NaN rows where there is none.
- ``solutions.npz`` (``ik.solutions`` > 1): every kept IK branch per grasp,
  rows in ``grasps.csv`` order (:func:`write_solutions`).

:func:`read_npz` reads any ``.npz`` an input names (a file of grasps, a
study's parts) with its headers checked and its size bounded.
"""

from __future__ import annotations

import dataclasses
import os
import stat
import struct
import zipfile
import zlib
from pathlib import Path
from typing import Any

import numpy as np

from gcm_pipeline.errors import InputError, clip
from gcm_pipeline.manifold.build import Manifold
from gcm_pipeline.table import GraspTable

#: What reading a damaged zip archive (an ``.npz``) raises: besides zipfile's own
#: errors, a member name cut to nothing at a NUL byte fails ``is_dir()`` with an
#: IndexError, a damaged extra field with struct.error, and a compression method
#: zipfile lacks with NotImplementedError.
ZIP_ERRORS = (
    zipfile.BadZipFile,
    zipfile.LargeZipFile,
    zlib.error,
    OSError,
    EOFError,
    ValueError,
    IndexError,
    struct.error,
    NotImplementedError,
)

__all__ = [
    "CONFIGURATION_COLUMNS",
    "SOLUTION_COLUMNS",
    "ZIP_ERRORS",
    "manifold_vertex_rows",
    "npy_header",
    "npy_layout",
    "open_regular",
    "read_manifold",
    "read_npz",
    "read_configurations",
    "write_configurations",
    "write_manifold",
    "write_solutions",
]


# ------------------------------------------------------------ .npy / .npz, checked

#: Most header bytes of one .npy array (NumPy's own default bound).
_MAX_NPY_HEADER = 10_000


def npy_header(
    path: Path, fh: Any, what: str, available: int
) -> tuple[tuple[int, ...], np.dtype[Any]]:
    """Shape and dtype of the .npy array at ``fh``; refuses a header that promises too much.

    :func:`npy_layout` with the storage order left out.
    """
    shape, _, dtype = npy_layout(path, fh, what, available)
    return shape, dtype


def npy_layout(
    path: Path, fh: Any, what: str, available: int
) -> tuple[tuple[int, ...], bool, np.dtype[Any]]:
    """Shape, Fortran order and dtype of the .npy array at ``fh`` (see below).

    Nothing is allocated: a header that claims 10^10 poses in a 1 kB file
    is an error here, not a MemoryError later.

    Args:
        path: The file (for messages).
        fh: A binary stream at the start of the .npy data.
        what: The array's name in messages.
        available: Bytes the stream holds from its start.

    Raises:
        InputError: Not a .npy header, a pickled object array, or more data
            promised than ``available``.
    """
    try:
        version = np.lib.format.read_magic(fh)
        if version == (1, 0):
            shape, fortran, dtype = np.lib.format.read_array_header_1_0(fh, _MAX_NPY_HEADER)
        else:
            shape, fortran, dtype = np.lib.format.read_array_header_2_0(fh, _MAX_NPY_HEADER)
    except Exception as exc:  # the header is parsed as Python literals: anything can go wrong
        raise InputError(
            f"{path}: {what} is not a .npy array: {clip(str(exc))}", path=path
        ) from None
    if dtype.hasobject:
        raise InputError(
            f"{path}: {what} holds Python objects (a pickle); only plain arrays are read", path=path
        )
    need = fh.tell() + int(np.prod(shape, dtype=object)) * dtype.itemsize
    if need > available:
        raise InputError(
            f"{path}: {what} is truncated or corrupt: its header says shape {shape} "
            f"({need:,} bytes) but there are {available:,}",
            path=path,
        )
    return tuple(int(k) for k in shape), bool(fortran), dtype


def open_regular(path: str | Path) -> Any:
    """Open ``path`` for binary reading without ever waiting on it: a regular file only.

    A named pipe would block ``open`` until a writer comes (and a device may
    never end): the file is opened with ``O_NONBLOCK`` and checked with
    ``fstat`` before a byte is read.

    Raises:
        InputError: It is a directory, a pipe, a device or a socket.
        OSError: It cannot be opened.
    """
    path = Path(path)
    fd = os.open(path, os.O_RDONLY | getattr(os, "O_NONBLOCK", 0))
    try:
        mode = os.fstat(fd).st_mode
        if not stat.S_ISREG(mode):
            what = "a directory" if stat.S_ISDIR(mode) else "not a regular file (a pipe or device)"
            raise InputError(f"{path}: it is {what}; a regular file is needed", path=path)
        if hasattr(os, "set_blocking"):
            os.set_blocking(fd, True)
        return os.fdopen(fd, "rb")
    except BaseException:
        os.close(fd)
        raise


def read_npz(path: str | Path, *, max_bytes: int, keep: Any = None) -> dict[str, np.ndarray]:
    """The arrays of an ``.npz`` file, each header checked before it is read.

    Args:
        path: The archive.
        max_bytes: Most bytes all arrays may take together.
        keep: Optional ``(name, shape, dtype) -> bool``: read only those arrays.

    Raises:
        InputError: Not a zip archive, a member that is not a .npy array,
            truncated or corrupt data (CRC), pickled objects, too large.
    """
    path = Path(path)
    try:
        with open_regular(path) as fh, zipfile.ZipFile(fh) as zf:
            infos = {}
            for info in zf.infolist():
                if info.is_dir():
                    continue
                if not info.filename.endswith(".npy"):
                    raise InputError(
                        f"{path}: member {clip(info.filename)} is not a .npy array; an .npz "
                        "holds arrays only",
                        path=path,
                    )
                infos[info.filename[: -len(".npy")]] = info
            total = sum(info.file_size for info in infos.values())
            if total > max_bytes:
                raise InputError(
                    f"{path}: its arrays take {total:,} bytes, more than the {max_bytes:,} "
                    "read here",
                    path=path,
                )
            arrays: dict[str, np.ndarray] = {}
            for name, info in infos.items():
                with zf.open(info) as fh:
                    shape, dtype = npy_header(path, fh, f"array {name!r}", info.file_size)
                if keep is not None and not keep(name, shape, dtype):
                    continue
                with zf.open(info) as fh:
                    arrays[name] = np.lib.format.read_array(fh, allow_pickle=False)
    except InputError:
        raise
    except ZIP_ERRORS as exc:
        raise InputError(
            f"{path}: not a readable .npz archive: {clip(str(exc) or type(exc).__name__)}",
            path=path,
        ) from None
    return arrays


# ------------------------------------------------------------ manifold.npz


def _manifold_arrays(manifold: Manifold) -> dict[str, Any]:
    """Every field of the manifold as an array (None fields left out)."""
    arrays: dict[str, Any] = {}
    for f in dataclasses.fields(manifold):
        value = getattr(manifold, f.name)
        if value is None or (f.name == "structure" and value == "chart"):
            continue  # the chart structure's file is the paper's, as before
        arr = np.asarray(value)
        if arr.dtype == object:
            arr = arr.astype(str)
        arrays[f.name] = arr
    arrays["vertex_ids"] = np.arange(len(manifold.chart), dtype=np.int64)
    arrays["triangles"] = np.asarray(manifold.triangles, dtype=np.int64).reshape(-1, 3)
    arrays["dropped"] = np.asarray(manifold.dropped, dtype=np.int64).reshape(-1, 3)
    arrays["dropped_reason"] = np.asarray(manifold.dropped_reason, dtype=str).reshape(-1)
    return arrays


def write_manifold(
    manifold: Manifold, path: str | Path, *, csv_rows: np.ndarray | None = None
) -> None:
    """Write ``manifold.npz`` (see :func:`read_manifold` for the arrays).

    Args:
        manifold: The manifold.
        path: The file to write.
        csv_rows: (V,) the ``grasps.csv`` data row (0-based) of each candidate
            (manifold vertex); default ``arange(V)``.
    """
    arrays = _manifold_arrays(manifold)
    if csv_rows is not None:
        arrays["vertex_ids"] = np.asarray(csv_rows, dtype=np.int64).reshape(-1)
    with Path(path).open("wb") as fh:
        np.savez(fh, **arrays)


#: Most bytes of a run's manifold.npz that are read.
_MAX_MANIFOLD_BYTES = 1 << 30


def read_manifold(path: str | Path, n_rows: int | None = None) -> Manifold:
    """Read ``manifold.npz`` back into a :class:`~gcm_pipeline.manifold.build.Manifold`.

    The file holds ``vertex_ids`` (V,): the ``grasps.csv`` data row (0-based)
    of each manifold vertex (candidate); ``chart`` (V, 2) [m]; ``triangles``
    (T, 3) and ``dropped`` (D, 3) vertex indices 0..V-1; ``dropped_reason``
    (D,); and every other field of the :class:`Manifold` that is not None
    (``projection``, ``triangulator``, the chart ``frame`` (4, 4), ``period``
    [m], ...). Shapes, dtypes and index ranges are checked.

    Args:
        path: The file.
        n_rows: Rows of the run's grasps.csv, to check ``vertex_ids`` against.

    Raises:
        InputError: Missing, unreadable or inconsistent file (names the array).
    """
    path = Path(path)
    if not path.is_file():
        raise InputError(f"not a run directory: {path} is missing")
    arrays = read_npz(path, max_bytes=_MAX_MANIFOLD_BYTES)
    missing = [k for k in ("chart", "triangles", "projection") if k not in arrays]
    if missing:
        raise InputError(f"{path}: missing array(s) {', '.join(missing)}", path=path)

    def fail(name: str, what: str) -> InputError:
        return InputError(f"{path}: array {name!r} {what}", path=path)

    chart = arrays["chart"]
    if chart.ndim != 2 or chart.shape[1] != 2 or chart.dtype.kind not in "fiu":
        raise fail("chart", f"must be (V, 2) numbers, got {chart.shape} {chart.dtype}")
    n_v = len(chart)
    for name in ("triangles", "dropped"):
        value = arrays.get(name, np.zeros((0, 3), dtype=np.int64))
        if value.size == 0:
            value = value.reshape(0, 3).astype(np.int64)
        if value.ndim != 2 or value.shape[1] != 3 or value.dtype.kind not in "iu":
            raise fail(name, f"must be (T, 3) integers, got {value.shape} {value.dtype}")
        if value.size and (value.min() < 0 or value.max() >= n_v):
            raise fail(name, f"has vertex ids outside 0..{n_v - 1}")
        arrays[name] = value.astype(np.int64)
    reason = arrays.get("dropped_reason", np.zeros(0, dtype=str)).reshape(-1)
    if len(reason) != len(arrays["dropped"]):
        raise fail("dropped_reason", f"has {len(reason)} values for {len(arrays['dropped'])}")
    arrays["dropped_reason"] = reason.astype(str)
    for name in ("projection", "triangulator"):
        if name in arrays and (arrays[name].ndim != 0 or arrays[name].dtype.kind != "U"):
            raise fail(name, "must be a text")
    if "frame" in arrays:
        frame = arrays["frame"]
        if frame.shape != (4, 4) or frame.dtype.kind not in "fiu":
            raise fail("frame", f"must be a (4, 4) transform, got {frame.shape}")
    if "period" in arrays and (arrays["period"].ndim != 0 or arrays["period"].dtype.kind != "f"):
        raise fail("period", "must be a number")
    for name, kinds in (("family", "iu"), ("isolation", "U")):
        if name in arrays and (
            arrays[name].shape != (n_v,) or arrays[name].dtype.kind not in kinds
        ):
            raise fail(name, f"must be ({n_v},) values, got {arrays[name].shape}")
    ids = arrays.get("vertex_ids", np.arange(n_v, dtype=np.int64))
    if ids.shape != (n_v,) or ids.dtype.kind not in "iu":
        raise fail("vertex_ids", f"must be ({n_v},) integers, got {ids.shape} {ids.dtype}")
    if n_rows is not None and n_v and (ids.min() < 0 or ids.max() >= n_rows):
        raise fail("vertex_ids", f"names rows outside grasps.csv (0..{n_rows - 1})")
    if len(np.unique(ids)) != n_v:
        raise fail("vertex_ids", "names a row twice")
    kwargs: dict[str, Any] = {}
    for f in dataclasses.fields(Manifold):
        if f.name in arrays:
            value = arrays[f.name]
            kwargs[f.name] = value.item() if value.ndim == 0 else value
    return Manifold(**kwargs)


def manifold_vertex_rows(path: str | Path, n: int) -> np.ndarray:
    """The ``vertex_ids`` of ``manifold.npz`` (grasps.csv rows of the candidates)."""
    arrays = read_npz(path, max_bytes=_MAX_MANIFOLD_BYTES, keep=lambda k, s, d: k == "vertex_ids")
    if "vertex_ids" in arrays:
        return np.asarray(arrays["vertex_ids"], dtype=np.int64)
    return np.arange(n)


#: Table columns of joint configurations written to ``configurations.npz``.
CONFIGURATION_COLUMNS = ("q", "q_pregrasp", "q_retreat", "q_rejected")


def write_configurations(grasps: GraspTable, path: str | Path, order: np.ndarray) -> None:
    """Write ``configurations.npz``: the (N, nq) configuration columns in csv row order.

    Args:
        grasps: The grasp table (columns of :data:`CONFIGURATION_COLUMNS` it has).
        path: The file.
        order: Table row of each csv row (as :func:`write_grasps_csv` returns).
    """
    arrays = {
        name: np.asarray(grasps[name], dtype=float)[order]
        for name in CONFIGURATION_COLUMNS
        if name in grasps and np.ndim(grasps[name]) == 2
    }
    with open(path, "wb") as fh:
        np.savez(fh, **arrays)


#: Columns of ``configurations.npz`` that ``grasps.csv`` does not hold (``q`` it does).
EXTRA_CONFIGURATION_COLUMNS = ("q_pregrasp", "q_retreat", "q_rejected")


def read_configurations(path: str | Path, n: int, nq: int) -> dict[str, np.ndarray]:
    """The approach, retreat and rejected configurations of ``configurations.npz`` (csv order).

    Args:
        path: The file (absent: nothing read).
        n: Rows of ``grasps.csv``.
        nq: Joints of the run's configurations (the ``q1 .. qN`` columns).

    Returns:
        ``{name: (n, nq) float}`` for each of :data:`EXTRA_CONFIGURATION_COLUMNS` the file holds.

    Raises:
        InputError: The file is damaged, or an array is not (n, nq) float (names it).
    """
    path = Path(path)
    if not path.is_file():
        return {}
    arrays = read_npz(
        path,
        max_bytes=len(CONFIGURATION_COLUMNS) * 8 * max(n, 1) * max(nq, 1) + 4096,
        keep=lambda name, shape, dtype: name in EXTRA_CONFIGURATION_COLUMNS,
    )
    for name, a in arrays.items():
        if a.shape != (n, nq) or a.dtype.kind != "f":
            raise InputError(
                f"{path}: array {name!r} is {a.dtype} {a.shape}; expected float ({n}, {nq}): "
                "one row per row of grasps.csv, one column per joint",
                path=path,
            )
    return {name: np.asarray(a, dtype=float) for name, a in arrays.items()}


#: Branch columns written to ``solutions.npz`` (``ik.solutions`` > 1) and their names there.
SOLUTION_COLUMNS = {
    "solutions": "q",
    "solutions_q_pregrasp": "q_pregrasp",
    "solutions_q_retreat": "q_retreat",
    "solutions_clearance": "clearance",
    "n_solutions": "count",
    "solution": "chosen",
}


def write_solutions(grasps: GraspTable, path: str | Path, order: np.ndarray) -> None:
    """Write ``solutions.npz``: every kept IK branch of every grasp, in csv row order.

    ``q``, ``q_pregrasp``, ``q_retreat`` (N, K, nq) [rad], ``clearance`` (N, K)
    [m], ``count`` (N,) branches kept, ``chosen`` (N,) the branch in
    ``grasps.csv`` (-1: unreachable); NaN past ``count``.
    """
    arrays = {
        name: np.asarray(grasps[col])[order]
        for col, name in SOLUTION_COLUMNS.items()
        if col in grasps
    }
    with open(path, "wb") as fh:
        np.savez(fh, **arrays)
