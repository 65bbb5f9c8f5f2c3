"""``format: npy``: one NumPy array (N, 4, 4) of grasp poses, its header checked first."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from gcm_pipeline.errors import InputError, clip
from gcm_pipeline.rundir.arrays import npy_header
from gcm_pipeline.sources.files.common import as_poses, check_count

__all__ = ["read_npy"]


def read_npy(path: Path, max_count: int) -> np.ndarray:
    """Poses (N, 4, 4) of an ``.npy`` file; the shape and count are checked from its header."""
    try:
        with path.open("rb") as fh:
            if fh.read(4) == b"PK\x03\x04":  # an npz is a zip archive
                raise InputError(
                    f"{path}: expected a .npy array, got an archive (use format: npz)", path=path
                )
            fh.seek(0)
            shape, _ = npy_header(path, fh, "the array", path.stat().st_size)
            if len(shape) != 3 or shape[1:] != (4, 4):
                raise InputError(
                    f"{path}: the array must have shape (N, 4, 4), got {shape}", path=path
                )
            check_count(path, shape[0], max_count)
            fh.seek(0)
            arr = np.lib.format.read_array(fh, allow_pickle=False)
    except OSError as exc:
        raise InputError(f"{path}: cannot read: {exc.strerror or exc}", path=path) from None
    except ValueError as exc:
        raise InputError(
            f"{path}: not a readable .npy array: {clip(str(exc))}", path=path
        ) from None
    return as_poses(path, arr, "the array")
