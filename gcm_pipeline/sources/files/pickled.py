"""Arrays of an ``.npz`` archive whose members may be pickled dicts, read without running code.

Contact-GraspNet stores its per-segment dicts with pickle, GraspNet tools plain
arrays. Pickled members are read by a restricted unpickler that only builds
NumPy arrays, dtypes and scalars (besides plain dicts, lists, numbers and
strings), each opcode counted, so a prediction file cannot run code or
expand to more than ``max_count`` grasps' worth of numbers.
"""

from __future__ import annotations

import pickle
import zipfile
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import numpy as np

from gcm_pipeline.errors import InputError, clip
from gcm_pipeline.rundir.arrays import ZIP_ERRORS, npy_header
from gcm_pipeline.sources.files.common import SLACK_BYTES, check_bytes

__all__ = ["read_npz_members", "read_pickled_npy"]

#: Bytes a grasp may take in a binary (.npy/.npz) file: a pose, scores, contacts,
#: openings and pickle framing.
BINARY_BYTES_PER_GRASP = 512

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


def read_npz_members(path: Path, max_count: int) -> dict[str, Any]:
    """Every array of an ``.npz``; object arrays through :class:`_ArrayUnpickler`.

    Sizes are checked before anything is read: all members together at most
    what ``max_count`` grasps take, and each plain array's header against
    the bytes its member holds.
    """
    out: dict[str, Any] = {}
    # numbers the pickled members may expand to: a pickle refers to one list or array
    # many times for a few bytes each, so its size on disk does not bound them
    budget = max_count * (BINARY_BYTES_PER_GRASP // 8) + SLACK_BYTES // 8
    values = 0
    try:
        with zipfile.ZipFile(path) as zf:
            infos = [i for i in zf.infolist() if i.filename.endswith(".npy")]
            total = sum(i.file_size for i in infos)
            check_bytes(path, total, max_count, BINARY_BYTES_PER_GRASP, "its arrays")
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
                                "per array); save it as plain arrays",
                                path=path,
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
    except (*ZIP_ERRORS, TypeError, SyntaxError, pickle.UnpicklingError) as exc:
        raise InputError(
            f"{path}: not a readable .npz archive: {clip(str(exc))}", path=path
        ) from None
    return out


def read_pickled_npy(path: Path, max_values: int) -> Any:
    """The object a ``.npy`` file holding a pickle (a 0-d object array) stores.

    Contact-GraspNet's ``.npy`` scenes are pickled dicts of arrays; read by
    :class:`_ArrayUnpickler` (no code runs), at most ``max_values`` numbers.

    Raises:
        InputError: Not a pickled ``.npy``, a pickle of anything else, too large.
    """
    try:
        with open(path, "rb") as fh:
            version = np.lib.format.read_magic(fh)
            if version == (1, 0):
                np.lib.format.read_array_header_1_0(fh)
            else:
                np.lib.format.read_array_header_2_0(fh)
            try:
                value = _ArrayUnpickler(fh).load()
            except _TooManySteps:
                raise InputError(
                    f"{path}: its pickle takes more than {_MAX_PICKLE_STEPS:,} steps; save "
                    "it as plain arrays",
                    path=path,
                ) from None
    except InputError:
        raise
    except (OSError, ValueError, EOFError, TypeError, pickle.UnpicklingError) as exc:
        raise InputError(
            f"{path}: not a readable pickled .npy: {clip(str(exc))}", path=path
        ) from None
    _count_values(path, "(the file)", value, max_values)
    if isinstance(value, np.ndarray) and value.dtype.hasobject and value.shape == ():
        value = value.item()
    return value


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
        "candidates.max_count grasps need; raise candidates.max_count to read it",
        path=path,
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
                f"{_MAX_NESTING} levels deep",
                path=path,
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
