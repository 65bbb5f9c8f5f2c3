"""``format: acronym``: ACRONYM's HDF5 grasp files, read in a forked child process.

Layout: ``grasps/transforms`` (N, 4, 4) poses of the Franka hand's base in the
object mesh frame [m], ``grasps/qualities/flex/object_in_gripper`` (N,) 0/1
success, optional ``object/file``, ``object/scale`` and ``gripper/type``.
The ``score`` column is ``object_in_gripper`` (1.0: the object stayed in the
simulated gripper, 0.0: it fell out): the one quality ACRONYM states per grasp.
Its ``object_motion_during_{closing,shaking}_{linear,angular}`` datasets
(how far the object moved, in mixed units) are not read and not turned into a score.
Reading needs the optional extra ``acronym`` (h5py, :data:`ACRONYM_INSTALL_HINT`).
"""

from __future__ import annotations

import contextlib
import logging
import math
import multiprocessing as mp
import signal
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from gcm_pipeline.bounds import MAX_HDF5_TEXT
from gcm_pipeline.errors import InputError, clip
from gcm_pipeline.sources.files.common import as_poses, check_count, score_column, success_labels

__all__ = ["ACRONYM_INSTALL_HINT", "read_acronym", "read_acronym_object"]

log = logging.getLogger(__name__)

ACRONYM_INSTALL_HINT = 'pip install "gcm-pipeline[acronym]"'

#: A child reading an ACRONYM file gets this long [s], plus a second per
#: ``_HDF5_BYTES_PER_SECOND`` of file, before the file counts as corrupt: the HDF5
#: library can loop forever on a damaged file (seen: a damaged variable-length string).
_HDF5_SECONDS = 10.0
_HDF5_BYTES_PER_SECOND = 20e6


def read_acronym(path: Path, max_count: int) -> tuple[np.ndarray, np.ndarray, str | None]:
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
            f"{path}: reading ACRONYM HDF5 files needs h5py: {ACRONYM_INSTALL_HINT}", path=path
        ) from None

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
            "the file is corrupt",
            path=path,
        )
    if result is None:
        code = child.exitcode or 0
        what = signal.Signals(-code).name if code < 0 else f"exit status {code}"
        raise InputError(
            f"{path}: reading it crashed the HDF5 library ({what}); the file is corrupt", path=path
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


#: What the HDF5 library (through h5py) raises on a corrupt or unreadable file.
_HDF5_ERRORS = (OSError, KeyError, RuntimeError, ValueError, TypeError)


@dataclass
class _Place:
    """Where in an HDF5 file reading is (``object``, ``grasps/transforms``), for the message."""

    at: str


@contextlib.contextmanager
def _hdf5_file(path: Path, at: str = "the file") -> Iterator[tuple[Any, _Place]]:
    """The open file ``path`` and the place being read; a library error is an :class:`InputError`.

    Any error the HDF5 library raises while the file is opened, read or
    closed becomes ``corrupt or unreadable HDF5 file (at <place>)``, naming
    the file and ``place.at`` as the reader last set it; an
    :class:`InputError` raised inside passes unchanged.
    """
    import h5py

    place = _Place(at)
    try:
        with h5py.File(path, "r") as fh:
            yield fh, place
    except InputError:
        raise
    except _HDF5_ERRORS as exc:
        raise InputError(
            f"{path}: corrupt or unreadable HDF5 file (at {place.at}): {clip(str(exc))}", path=path
        ) from None


def _read_acronym_here(path: Path, max_count: int) -> tuple[np.ndarray, np.ndarray, str | None]:
    """Poses, success labels and ``gripper/type`` (e.g. ``panda``, or None) of an ACRONYM file."""
    import h5py

    with _hdf5_file(path) as (fh, where):
        datasets = {}
        for key in ("grasps/transforms", "grasps/qualities/flex/object_in_gripper"):
            where.at = key
            if key not in fh:
                raise InputError(
                    f"{path}: not an ACRONYM grasp file: missing dataset {key!r}", path=path
                )
            node = fh[key]
            if not isinstance(node, h5py.Dataset):
                raise InputError(
                    f"{path}: {key} is a {type(node).__name__}, not a dataset", path=path
                )
            if node.dtype.kind not in "biuf":
                raise InputError(
                    f"{path}: {key} must hold numbers, got dtype {node.dtype}", path=path
                )
            datasets[key] = node
        where.at = "grasps/transforms"
        tf = datasets["grasps/transforms"]
        if len(tf.shape) != 3 or tf.shape[1:] != (4, 4):
            raise InputError(
                f"{path}: grasps/transforms must have shape (N, 4, 4), got {tf.shape}",
                path=path,
            )
        check_count(path, tf.shape[0], max_count)
        poses = as_poses(path, np.asarray(tf[()]), "grasps/transforms")
        where.at = "grasps/qualities/flex/object_in_gripper"
        quality = datasets[where.at]
        if quality.size != poses.shape[0]:
            raise InputError(
                f"{path}: {where.at} has {quality.size} values, expected {poses.shape[0]}",
                path=path,
            )
        raw = score_column(path, quality[()], poses.shape[0], where.at)  # the score's source
        success = success_labels(path, raw, poses.shape[0], where.at)
        where.at = "object"
        name, scale = _acronym_object(path, fh, h5py)
        where.at = "gripper/type"
        gripper = _h5_text(path, fh, h5py, "gripper/type")
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
        raise InputError(f"{path}: {key} must be {what}, got a {type(node).__name__}", path=path)
    declared = int(np.prod(node.shape, dtype=object)) * node.dtype.itemsize
    if declared > max_bytes:
        raise InputError(
            f"{path}: {key} declares {declared:,} bytes (shape {node.shape}, dtype "
            f"{node.dtype}); {what} takes at most {max_bytes:,}: the file is corrupt",
            path=path,
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
        raise InputError(f"{path}: {key} must be a text, got {clip(raw)}", path=path)
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
            raise InputError(f"{path}: object/scale must be a number, got {clip(raw)}", path=path)
        scale = float(raw)
        if not (math.isfinite(scale) and scale > 0):
            raise InputError(
                f"{path}: object/scale must be a positive number, got {scale!r}", path=path
            )
    return name, scale


def read_acronym_object(path: Path) -> tuple[str | None, float]:
    """``object/file`` (None when missing) and ``object/scale`` (1 when missing) of a file.

    Read in this process: call it after :func:`read_acronym` has read the
    same file in a child (which checks both keys), so a corrupt file has
    already been refused.

    Raises:
        InputError: An unreadable file, or a scale that is not a positive finite number.
    """
    import h5py

    with _hdf5_file(path, "object") as (fh, _):
        return _acronym_object(path, fh, h5py)
