"""The run directory: written atomically, read back for ``gcm show`` / ``gcm plot``.

A run directory holds (see DESIGN.md, *Run directory*):

- ``grasps.csv``: one row per grasp, ranked rows first (rank 1 = best), then
  the unreachable ones in table order. Columns, in this order: ``rank, origin,
  triangle, v1, v2, v3, w1, w2, w3, x, y, z, qw, qx, qy, qz, reachable,
  reason, pos_err, rot_err, manipulability, q1 .. q{nq}``, then any further
  metric columns, then the per-candidate columns of the source
  (:data:`~gcm_pipeline.table.CANDIDATE_COLUMNS`: ``score``, ``width``,
  ``source_id``, ...; integers as integers, strings quoted when needed).
  Poses are the grasp frame in the world (quaternion with ``qw >= 0``).
  Floats are written with :func:`repr` (they round-trip exactly); NaN is an
  empty cell; booleans are ``true`` / ``false``.
- ``summary.json``: counts, timings [s], the ranking's top grasps, the
  resolved config and package versions.
- ``manifold.npz``: ``vertex_ids``, ``chart``, ``triangles``, ``dropped``,
  ``dropped_reason``, ``projection``, ``triangulator`` and the chart ``frame``.
- ``configurations.npz``: the joint configurations [rad], one (N, nq) array
  per table column, rows in ``grasps.csv`` order: ``q`` (the solution),
  ``q_pregrasp`` (end of the approach), ``q_retreat`` (end of the retreat)
  and ``q_rejected`` (for unreachable grasps, the IK solution that collided
  or whose approach or retreat failed); NaN rows where there is none.
- ``solutions.npz`` (``ik.solutions`` > 1): every kept IK branch per grasp,
  rows in ``grasps.csv`` order (:func:`write_solutions`).
- ``config.yaml``: the resolved config.
- optional ``scene.html`` and ``*.png`` from the publish stage.

- ``.gcm.json``: the marker that says gcm_pipeline wrote the directory
  (:func:`write_marker`); only a directory with a valid marker is ever
  replaced, whatever other files it holds.

Everything is written into a temporary sibling directory
(``.<name>.tmp-<pid>-<random>``, marker first) that is renamed to the final
name only when complete (:func:`atomic_dir`); on any failure, Ctrl-C
included, the temporary directory is removed, so a directory named like the
run is always complete. With ``force`` an existing run is replaced only at
that final rename, with the parent directory locked (concurrent runs into
one place take turns) and signals held until the swap is done. The same
machinery serves other directory kinds (``atomic_dir(path, kind="study")``).
"""

from __future__ import annotations

import contextlib
import csv
import dataclasses
import errno
import json
import logging
import math
import os
import platform
import re
import shutil
import signal
import stat
import sys
import tempfile
import threading
import time
import uuid
import zipfile
import zlib
from collections.abc import Iterable, Iterator, Mapping
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np
import yaml

from gcm_pipeline import interrupts
from gcm_pipeline.errors import InputError, OutputError, clip
from gcm_pipeline.geometry.dualquat import dq_from_pos_quat, dq_to_pos_quat
from gcm_pipeline.limits import MAX_CSV_CELL
from gcm_pipeline.stages.manifold import Manifold
from gcm_pipeline.table import CANDIDATE_COLUMNS, GraspTable

__all__ = [
    "CSV_COLUMNS",
    "MARKER",
    "RunData",
    "atomic_dir",
    "atomic_run_dir",
    "check_csv_cells",
    "check_output_dir",
    "disk_full",
    "format_floats",
    "is_project_dir",
    "looks_like_run_dir",
    "open_regular",
    "read_marker",
    "read_npz",
    "read_summary",
    "npy_header",
    "read_grasps_csv",
    "read_manifold",
    "read_run",
    "write_config",
    "write_configurations",
    "write_solutions",
    "write_grasps_csv",
    "write_manifold",
    "write_run_files",
    "write_marker",
    "write_summary",
]

log = logging.getLogger(__name__)

#: Fixed leading columns of ``grasps.csv`` (then ``q1 .. q{nq}`` and extra metrics).
CSV_COLUMNS = (
    "rank",
    "origin",
    "triangle",
    "v1",
    "v2",
    "v3",
    "w1",
    "w2",
    "w3",
    "x",
    "y",
    "z",
    "qw",
    "qx",
    "qy",
    "qz",
    "reachable",
    "reason",
    "pos_err",
    "rot_err",
    "manipulability",
)

#: Table columns that grasps.csv writes under other names (or derives).
_KNOWN = {"dq", "rank", "origin", "triangle", "vertices", "weights", "reachable", "reason"}
_KNOWN |= {"q", "pos_err", "rot_err", "manipulability"}

RUN_FILES = ("grasps.csv", "summary.json", "manifold.npz", "config.yaml")


# ------------------------------------------------------------ project directories

#: Marker file of a directory written by this project (run, study, ...).
MARKER = ".gcm.json"
_PROJECT = "gcm_pipeline"
_MAX_MARKER_BYTES = 4096
_ID = re.compile(r"[0-9a-f]{32}")


def write_marker(directory: str | Path, kind: str = "run") -> str:
    """Mark ``directory`` as written by gcm_pipeline (the ``.gcm.json`` marker).

    The marker is a small JSON object ``{"project": "gcm_pipeline", "kind":
    kind, "id": <32 hex digits>, "created": <UTC time>, "version": ...}``.
    Only a directory with a valid marker of the right kind is ever replaced
    (:func:`is_project_dir`); :func:`atomic_dir` writes it into the temporary
    directory before anything else.

    Args:
        directory: An existing directory.
        kind: What the directory holds (``run``, ``study``, ...).

    Returns:
        The new id.
    """
    from gcm_pipeline import __version__

    ident = uuid.uuid4().hex
    marker = {
        "project": _PROJECT,
        "kind": kind,
        "id": ident,
        "created": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
        "version": __version__,
    }
    (Path(directory) / MARKER).write_text(json.dumps(marker) + "\n", encoding="utf-8")
    return ident


def read_marker(directory: str | Path) -> dict[str, Any] | None:
    """The marker of a project directory, or None (missing, unreadable or not ours).

    A marker is valid when it is a JSON object of at most 4 kB with
    ``project == "gcm_pipeline"``, a string ``kind`` and a 32-hex-digit ``id``.
    """
    path = Path(directory) / MARKER
    try:
        if not path.is_file() or path.is_symlink():
            return None
        with path.open("rb") as fh:
            raw = fh.read(_MAX_MARKER_BYTES + 1)
        if len(raw) > _MAX_MARKER_BYTES:
            return None
        data = json.loads(raw.decode("utf-8"))
    except (OSError, ValueError):
        return None
    if (
        not isinstance(data, dict)
        or data.get("project") != _PROJECT
        or not isinstance(data.get("kind"), str)
        or not isinstance(data.get("id"), str)
        or _ID.fullmatch(data["id"]) is None
    ):
        return None
    return data


def is_project_dir(path: str | Path, kind: str = "run") -> bool:
    """Whether ``path`` is a directory that gcm_pipeline wrote as a ``kind``.

    Decided by its marker (:func:`write_marker`) alone: file names prove
    nothing (``summary.json`` and ``grasps.csv`` are easy to have). Only such a
    directory may be replaced with ``force``.
    """
    p = Path(path)
    if p.is_symlink() or not p.is_dir():
        return False
    marker = read_marker(p)
    return marker is not None and marker["kind"] == kind


def looks_like_run_dir(path: str | Path) -> bool:
    """Whether ``path`` is a run directory written by gcm_pipeline (see :func:`is_project_dir`)."""
    return is_project_dir(path, "run")


# ------------------------------------------------------------ output checks


def _nearest_existing(path: Path) -> Path:
    p = path
    while not p.exists() and p != p.parent:
        p = p.parent
    return p


def _is_within(path: Path, root: Path) -> bool:
    """Whether ``path`` is ``root`` or lies inside it (both resolved)."""
    try:
        path.resolve().relative_to(root.resolve())
    except (ValueError, OSError):
        return False
    return True


def _check_replaceable(
    out: Path, *, force: bool, keep: Iterable[str | Path] = (), kind: str = "run"
) -> None:
    """Refuse to use an existing ``out`` that must not be replaced.

    ``out`` (which exists) may be replaced when it is an empty directory, or,
    with ``force``, when it is a ``kind`` directory of this project (its
    marker); never when it is a symbolic link, the working directory or one
    of its ancestors, or holds one of ``keep``.

    Raises:
        OutputError: Naming ``out`` and why.
    """
    if out.is_symlink():
        raise OutputError(
            f"refusing to replace {out}: it is a symbolic link; give the directory it points to "
            "or choose another --out"
        )
    if not out.is_dir():
        raise OutputError(f"output path {out} exists and is not a directory")
    if _is_within(Path.cwd(), out):
        raise OutputError(
            f"refusing to replace {out}: it is the working directory or one of its "
            "parents; choose another --out"
        )
    for item in keep:
        if _is_within(Path(item), out):
            raise OutputError(
                f"refusing to replace {out}: it holds {item}, an input of this run; "
                "choose another --out"
            )
    try:
        empty = not any(out.iterdir())
    except OSError as exc:
        raise OutputError(f"cannot read output directory {out}: {exc.strerror or exc}") from None
    if empty:
        return
    if not is_project_dir(out, kind):
        other = (read_marker(out) or {}).get("kind")
        if other is not None and other != kind:
            raise OutputError(
                f"refusing to replace {out}: it is a gcm {other[:40]} directory, not a "
                f"{kind} directory; choose another --out"
            )
        raise OutputError(
            f"refusing to replace {out}: it is not a gcm {kind} directory (no valid {MARKER} "
            "marker, which gcm writes into every run); choose another --out"
        )
    if not force:
        raise OutputError(
            f"output directory {out} already exists and is not empty; pass --force (CLI) "
            "or force=True (Python) to replace it, or choose another --out"
        )


def check_output_dir(
    path: str | Path,
    *,
    force: bool = False,
    keep: Iterable[str | Path] = (),
    kind: str = "run",
) -> Path:
    """Check, before any work, that a ``kind`` directory can be written at ``path``.

    An existing directory is used only if it is empty, or, with ``force``,
    if it is a previous directory of this kind (:func:`is_project_dir`);
    never a symbolic link, the working directory or one of its ancestors,
    nor a directory that holds one of ``keep`` (the config file and other
    inputs of the run).

    Args:
        path: The run directory to be.
        force: Allow replacing an existing previous run directory.
        keep: Files that must not be inside a directory being replaced.
        kind: The marker kind (``run``; ``study`` for a study directory).

    Returns:
        The absolute path.

    Raises:
        OutputError: ``path`` is a file; it is a non-empty directory and
            ``force`` is false or it is not a project directory; it is the
            working directory, an ancestor of it or holds one of ``keep``; a
            parent is a file or not writable.
    """
    out = Path(path).expanduser().absolute()
    keep = tuple(keep)
    try:
        exists = out.exists() or out.is_symlink()
    except (OSError, ValueError) as exc:
        raise OutputError(f"bad output path {clip(str(out))}: {exc}") from None
    if exists:
        # with the parent locked: a concurrent writer's swap (old directory renamed
        # aside, new one renamed in) must not be seen half done
        with _locked(out.parent):
            if out.exists() or out.is_symlink():
                _check_replaceable(out, force=force, keep=keep, kind=kind)
    parent = _nearest_existing(out.parent)
    if not parent.is_dir():
        raise OutputError(f"cannot create output directory {out}: {parent} is not a directory")
    # os.access is not enough (root, read-only mounts): try it for real.
    try:
        probe = tempfile.mkdtemp(prefix=f".{out.name}.probe-", dir=parent)
    except OSError as exc:
        raise OutputError(
            f"cannot create output directory {out}: {parent} is not writable ({exc.strerror})"
        ) from None
    os.rmdir(probe)
    return out


_SIGNALS = tuple(
    getattr(signal, name) for name in ("SIGINT", "SIGTERM", "SIGHUP") if hasattr(signal, name)
)


@contextlib.contextmanager
def _signals_deferred() -> Iterator[None]:
    """Hold Ctrl-C, SIGTERM and SIGHUP until the block is done (they arrive afterwards).

    Used around the few renames that swap a directory in, and around the
    clean-up after a failure, so that an interrupt cannot leave them half done.
    """
    block = getattr(signal, "pthread_sigmask", None)
    if block is None or threading.current_thread() is not threading.main_thread():
        yield
        return
    previous = block(signal.SIG_BLOCK, _SIGNALS)
    try:
        yield
    finally:
        block(signal.SIG_SETMASK, previous)


@contextlib.contextmanager
def _locked(directory: Path) -> Iterator[None]:
    """An exclusive advisory lock on ``directory`` (``flock`` on the directory itself).

    Serialises the replacement of siblings inside it between processes;
    nothing is created, so nothing is left behind. Where ``flock`` is not
    available the block runs unlocked.
    """
    try:
        import fcntl
    except ImportError:  # pragma: no cover - not POSIX
        yield
        return
    try:
        fd = os.open(directory, os.O_RDONLY)
    except OSError:
        yield
        return
    try:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX)
        except OSError:  # pragma: no cover - filesystem without locks
            pass
        yield
    finally:
        os.close(fd)  # releases the lock


def _pid_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except (PermissionError, OverflowError):
        return True
    return True


def _remove_stale(out: Path) -> None:
    """Remove ``.<name>.tmp-<pid>-*`` / ``.<name>.old-<pid>-*`` of processes that died.

    A process killed with SIGKILL cannot clean up; the next run into the
    same place does, for directories that carry this project's marker and
    whose process no longer exists (called with the parent locked).
    """
    pattern = re.compile(re.escape(f".{out.name}.") + r"(tmp|old)-(\d+)-[A-Za-z0-9_]+")
    try:
        entries = list(out.parent.iterdir())
    except OSError:
        return
    for entry in entries:
        match = pattern.fullmatch(entry.name)
        if match is None or int(match.group(2)) == os.getpid():
            continue
        if _pid_alive(int(match.group(2))) or read_marker(entry) is None:
            continue
        log.info("removing %s, left by a process that no longer runs", entry)
        shutil.rmtree(entry, ignore_errors=True)


def _unremovable(root: Path) -> str | None:
    """Why ``root``'s tree cannot be deleted, or None (checked before a swap).

    Deleting needs write and search permission on every directory of the
    tree and no immutable or append-only flag (``chattr +i`` / ``+a``, which
    stop even root).
    """
    for dirpath, dirnames, filenames in os.walk(root, onerror=None):
        here = Path(dirpath)
        if not os.access(here, os.W_OK | os.X_OK):
            return f"{here} is not writable"
        for name in [*dirnames, *filenames, ""]:
            path = here / name if name else here
            flag = _inode_flags(path)
            if flag:
                return f"{path} is {flag}"
    return None


def _inode_flags(path: Path) -> str:
    """``immutable`` / ``append-only`` for a Linux inode with that flag (``lsattr``), else ''."""
    if not sys.platform.startswith("linux") or path.is_symlink():
        return ""
    try:
        import array
        import fcntl

        fd = os.open(path, os.O_RDONLY | getattr(os, "O_NONBLOCK", 0))
    except (ImportError, OSError):
        return ""
    try:
        buf = array.array("l", [0])
        fcntl.ioctl(fd, 0x80086601, buf, True)  # FS_IOC_GETFLAGS
    except OSError:
        return ""
    finally:
        os.close(fd)
    flags = buf[0]
    if flags & 0x10:  # FS_IMMUTABLE_FL
        return "immutable"
    if flags & 0x20:  # FS_APPEND_FL
        return "append-only"
    return ""


@contextlib.contextmanager
def atomic_dir(
    path: str | Path,
    *,
    kind: str = "run",
    force: bool = False,
    keep: Iterable[str | Path] = (),
) -> Iterator[Path]:
    """Yield a temporary sibling directory that becomes ``path`` when the block succeeds.

    The temporary directory ``.<name>.tmp-<pid>-<random>`` gets this project's
    marker (:func:`write_marker`, kind ``kind``) first. On a clean exit of
    the ``with`` block it is renamed to ``path``; an existing directory there
    is replaced only then, and only when it is empty or, with ``force``, a
    ``kind`` directory of this project (checked again, with the parent
    locked, so concurrent writers of one ``path`` take turns: the last one
    wins and nothing else is left). Signals wait until the swap is done.

    On any exception, including :class:`KeyboardInterrupt` (Ctrl-C, and
    SIGTERM/SIGHUP under ``gcm``), the temporary directory is removed and the
    exception propagates; an existing ``path`` is left untouched.

    Args:
        path: The directory to write.
        kind: The marker kind (``run``, ``study``, ...).
        force: Replace an existing directory of this kind.
        keep: Files whose folders must never be replaced (inputs).

    Raises:
        OutputError: See :func:`check_output_dir`; the previous directory
            cannot be moved or removed (permissions, immutable files): it is
            left as it was.
    """
    keep = tuple(keep)
    out = check_output_dir(path, force=force, keep=keep, kind=kind)
    created = _missing_parents(out)
    tmp: Path | None = None
    try:
        out.parent.mkdir(parents=True, exist_ok=True)
        tmp = Path(tempfile.mkdtemp(prefix=f".{out.name}.tmp-{os.getpid()}-", dir=out.parent))
        write_marker(tmp, kind)
    except OSError as exc:
        if tmp is not None:
            shutil.rmtree(tmp, ignore_errors=True)
        _remove_empty(created)
        raise OutputError(f"cannot create output directory {out}: {exc}") from None
    try:
        yield tmp
        interrupts.check()  # an interrupt dropped while the block ran still stops the swap
        os.chmod(tmp, 0o755 & ~_umask())
        with _locked(out.parent):
            with _signals_deferred():
                _replace_dir(tmp, out, force=force, keep=keep, kind=kind)
                _remove_stale(out)
    except BaseException as exc:
        with _signals_deferred():
            shutil.rmtree(tmp, ignore_errors=True)
            _remove_empty(created)
        full = disk_full(out, exc, "nothing was written")
        if full is not None:
            raise full from None
        raise


#: The errors of a file system that has no room left (space, quota, file size).
_DISK_FULL = (errno.ENOSPC, errno.EDQUOT, errno.EFBIG)


def disk_full(path: str | Path, exc: BaseException, outcome: str) -> OutputError | None:
    """The one-line error for ``exc`` when it says the file system of ``path`` is full, else None.

    Args:
        path: What was being written (named in the message).
        exc: The exception a write raised.
        outcome: What is left, e.g. ``"nothing was written"``.
    """
    if not isinstance(exc, OSError) or exc.errno not in _DISK_FULL:
        return None
    code = errno.errorcode.get(exc.errno, str(exc.errno))
    return OutputError(
        f"cannot write {path}: {os.strerror(exc.errno)} ({code}); {outcome}; free some space "
        "or choose another --out"
    )


def atomic_run_dir(
    path: str | Path, *, force: bool = False, keep: Iterable[str | Path] = ()
) -> contextlib.AbstractContextManager[Path]:
    """:func:`atomic_dir` for a run directory (marker kind ``run``)."""
    return atomic_dir(path, kind="run", force=force, keep=keep)


def _missing_parents(out: Path) -> list[Path]:
    """The parents of ``out`` that do not exist yet, deepest first."""
    missing = []
    p = out.parent
    while not p.exists() and p != p.parent:
        missing.append(p)
        p = p.parent
    return missing


def _remove_empty(dirs: list[Path]) -> None:
    """Remove directories created for a run that failed (deepest first, if empty)."""
    for d in dirs:
        try:
            d.rmdir()
        except OSError:
            return


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


def _replace_dir(
    tmp: Path, out: Path, *, force: bool, keep: tuple[str | Path, ...], kind: str
) -> None:
    """Rename ``tmp`` to ``out``, replacing an existing ``out`` (checked again here).

    Called with the parent locked and signals deferred. The old directory is
    first renamed aside (``.<name>.old-<pid>-<random>``), the new one renamed
    in, then the old one deleted; a failure before the new one is in puts the
    old one back.
    """
    old: Path | None = None
    if out.exists() or out.is_symlink():
        _check_replaceable(out, force=force, keep=keep, kind=kind)
        why = _unremovable(out)
        if why is not None:
            raise OutputError(
                f"cannot replace {out}: {why}, so it cannot be removed; it is left as it was"
            )
        old = out.parent / f".{out.name}.old-{os.getpid()}-{uuid.uuid4().hex[:8]}"
        try:
            os.rename(out, old)
        except OSError as exc:
            raise OutputError(
                f"cannot replace {out}: {exc.strerror or exc}; it is left as it was"
            ) from None
    try:
        os.rename(tmp, out)
    except OSError as exc:
        if old is not None:
            os.rename(old, out)
        raise OutputError(f"cannot move the finished run into {out}: {exc}") from None
    if old is not None:
        try:
            shutil.rmtree(old)
        except OSError as exc:
            log.warning("could not remove the previous %s at %s: %s", kind, old, exc)


# ------------------------------------------------------------ grasps.csv


def format_floats(values: np.ndarray) -> list[str]:
    """Floats as :func:`repr` strings (round-trip exact); NaN as ``""``."""
    floats = np.asarray(values, dtype=float).reshape(-1).tolist()
    if not floats:
        return []
    # str() of a list reprs every float in C: ~2x faster than a comprehension
    return str(floats)[1:-1].replace("nan", "").split(", ")


def _quote(text: str) -> str:
    """A CSV field (quoted only when it has to be)."""
    if any(c in text for c in ',"\n\r'):
        return '"' + text.replace('"', '""') + '"'
    return text


def _ints(values: np.ndarray) -> list[str]:
    return [str(v) for v in np.asarray(values, dtype=np.int64).tolist()]


def _row_order(grasps: GraspTable) -> np.ndarray:
    """Ranked rows by rank, then the unranked rows in table order."""
    n = len(grasps)
    rank = grasps.get("rank")
    if rank is None:
        return np.arange(n)
    rank = np.asarray(rank, dtype=np.int64)
    key = np.where(rank > 0, rank, np.iinfo(np.int64).max)
    return np.argsort(key, kind="stable")


def _extra_columns(grasps: GraspTable) -> list[str]:
    """Further 1-D columns: metrics first, then per-candidate columns, each in table order.

    Numeric, boolean and string columns are written; per-candidate columns
    are the ones named in :data:`~gcm_pipeline.table.CANDIDATE_COLUMNS`.
    """
    extra = []
    for name in grasps.columns:
        col = grasps[name]
        if name in _KNOWN or col.ndim != 1:
            continue
        if np.issubdtype(col.dtype, np.number) or col.dtype == bool or col.dtype.kind in "US":
            extra.append(name)
    return [n for n in extra if n not in CANDIDATE_COLUMNS] + [
        n for n in extra if n in CANDIDATE_COLUMNS
    ]


def _cells(values: np.ndarray) -> list[str]:
    """CSV cells of a 1-D column by dtype: bool, int, float (repr) or quoted text."""
    kind = values.dtype.kind
    if kind == "b":
        return ["true" if b else "false" for b in values.tolist()]
    if kind in "iu":
        return _ints(values)
    if kind in "US":
        return [_quote(str(v)) for v in values.tolist()]
    return format_floats(values)


def write_grasps_csv(grasps: GraspTable, path: str | Path) -> np.ndarray:
    """Write the grasp table as ``grasps.csv`` (see the module docstring).

    Args:
        grasps: The table; ``dq`` is required, every other column optional
            (missing ones are empty cells).
        path: The file to write.

    Returns:
        (N,) the table row written as each data row of the file (ranked first).
        The ``v1, v2, v3`` cells name data rows of this file (0-based, the
        header not counted), not table rows.
    """
    order = _row_order(grasps)
    g = grasps.take(order)
    n = len(g)
    empty = [""] * n
    csv_row = np.empty(n, dtype=np.int64)
    csv_row[order] = np.arange(n)
    pos, quat = dq_to_pos_quat(g["dq"])
    quat = np.where(quat[:, :1] < 0, -quat, quat)  # same rotation, qw >= 0

    def col(name: str, fmt: Any) -> list[str]:
        return fmt(g[name]) if name in g else empty

    def bools(v: np.ndarray) -> list[str]:
        return ["true" if b else "false" for b in np.asarray(v, dtype=bool).tolist()]

    def strs(v: np.ndarray) -> list[str]:
        return [_quote(str(s)) for s in np.asarray(v).tolist()]

    cols: list[list[str]] = [col("rank", _ints), col("origin", strs), col("triangle", _ints)]
    if "vertices" in g:  # table rows -> the data rows of this file that hold them
        vert = np.asarray(g["vertices"], dtype=np.int64).reshape(n, 3)
        ok = (vert >= 0) & (vert < n)
        vert = np.where(ok, csv_row[np.where(ok, vert, 0)], vert)
    for k in range(3):
        cols.append(_ints(vert[:, k]) if "vertices" in g else empty)
    for k in range(3):
        cols.append(format_floats(g["weights"][:, k]) if "weights" in g else empty)
    cols += [format_floats(pos[:, k]) for k in range(3)]
    cols += [format_floats(quat[:, k]) for k in range(4)]
    cols += [col("reachable", bools), col("reason", strs)]
    cols += [col(name, format_floats) for name in ("pos_err", "rot_err", "manipulability")]
    header = list(CSV_COLUMNS)
    if "q" in g:
        q = np.asarray(g["q"], dtype=float)
        q = q.reshape(n, q.shape[1] if q.ndim == 2 else 1)
        header += [f"q{j + 1}" for j in range(q.shape[1])]
        cols += [format_floats(q[:, j]) for j in range(q.shape[1])]
    for name in _extra_columns(g):
        header.append(name)
        cols.append(_cells(np.asarray(g[name])))
    with Path(path).open("w", newline="", encoding="utf-8") as fh:
        fh.write(",".join(header) + "\n")
        fh.writelines(",".join(row) + "\n" for row in zip(*cols, strict=True))
    return order


#: Most bytes of a run's summary.json that are read.
_MAX_SUMMARY_BYTES = 64 << 20


def read_grasps_csv(path: str | Path) -> GraspTable:
    """Read ``grasps.csv`` back into a grasp table (``dq`` rebuilt from x..qz).

    Rows stay in file order (ranked first), so ``vertices`` (from ``v1, v2,
    v3``) index the table's rows. Columns: ``dq``, ``rank``, ``origin``,
    ``triangle``, ``vertices``, ``weights``, ``reachable``, ``reason``,
    ``pos_err``, ``rot_err``, ``manipulability``, ``q`` and the further
    columns, as far as the file has them.

    The file is checked as it is read: unit quaternions, finite positions,
    ``true``/``false`` switches, integer ids, ``v1..v3`` that name rows of the
    file; a UTF-8 byte order mark and blank lines are ignored.

    Raises:
        InputError: Missing file or columns, or a value that does not parse
            (names the line and column).
    """
    path = Path(path)
    try:
        with path.open(newline="", encoding="utf-8-sig") as fh:
            reader = csv.reader(fh)
            rows: list[list[str]] = []
            lines: list[int] = []
            for row in reader:
                if any(cell.strip() for cell in row):
                    check_csv_cells(path, reader.line_num, rows[0] if rows else None, row)
                    rows.append(row)
                    lines.append(reader.line_num)
    except FileNotFoundError:
        raise InputError(f"not a run directory: {path} is missing") from None
    except UnicodeDecodeError as exc:
        raise InputError(f"{path}: not UTF-8 text ({exc.reason} at byte {exc.start})") from None
    except (OSError, csv.Error) as exc:
        raise InputError(f"{path}: cannot read: {clip(str(exc))}") from None
    if not rows:
        raise InputError(f"{path}: empty file")
    header, body, lines = rows[0], rows[1:], lines[1:]
    if len(set(header)) != len(header):
        twice = next(h for h in header if header.count(h) > 1)
        raise InputError(f"{path}: the header names column {clip(twice)} twice")
    missing = [c for c in ("x", "y", "z", "qw", "qx", "qy", "qz") if c not in header]
    if missing:
        raise InputError(f"{path}: missing column(s) {', '.join(missing)}")
    for row, line in zip(body, lines, strict=True):
        if len(row) != len(header):
            raise InputError(f"{path}:{line}: {len(row)} fields, header has {len(header)}")
    n = len(body)
    # Python strings: a fixed-width array is as wide as the longest cell in every cell
    cells = np.empty((n, len(header)), dtype=object)
    if body:
        cells[:] = body
    raw = {name: cells[:, k] for k, name in enumerate(header)}

    def bad(name: str, i: int, what: str) -> InputError:
        return InputError(f"{path}:{lines[i]}: column {name!r}: {what}: {clip(str(raw[name][i]))}")

    def floats(name: str) -> np.ndarray:
        col = np.where(raw[name] == "", "nan", raw[name])
        try:
            return col.astype(float)
        except ValueError:
            for i, text in enumerate(col.tolist()):
                try:
                    float(text)
                except ValueError:
                    raise bad(name, i, "not a number") from None
            raise  # pragma: no cover

    def ints(name: str) -> np.ndarray:
        col = raw[name]
        ok = np.array([re.fullmatch(r"-?[0-9]{1,18}", t) is not None for t in col.tolist()])
        if n and not ok.all():
            raise bad(name, int(np.flatnonzero(~ok)[0]), "not an integer")
        return col.astype(np.int64).reshape(n)

    pos = np.column_stack([floats(c) for c in ("x", "y", "z")]).reshape(n, 3)
    quat = np.column_stack([floats(c) for c in ("qw", "qx", "qy", "qz")]).reshape(n, 4)
    broken = ~np.isfinite(pos).all(axis=1) | ~np.isfinite(quat).all(axis=1)
    with np.errstate(invalid="ignore"):
        broken |= np.abs(np.linalg.norm(quat, axis=1) - 1.0) > 1e-6
    if broken.any():
        i = int(np.flatnonzero(broken)[0])
        raise InputError(
            f"{path}:{lines[i]}: not a pose: x,y,z must be finite and qw,qx,qy,qz a unit "
            f"quaternion, got {pos[i].tolist()} and {quat[i].tolist()}"
        )
    cols: dict[str, Any] = {"dq": dq_from_pos_quat(pos, quat)}
    if "rank" in raw:
        cols["rank"] = ints("rank")
        if (cols["rank"] < 0).any():
            raise bad("rank", int(np.flatnonzero(cols["rank"] < 0)[0]), "negative")
    if "origin" in raw:
        cols["origin"] = raw["origin"].astype(str)
        odd = ~np.isin(cols["origin"], ("candidate", "interpolated", ""))
        if odd.any():
            raise bad("origin", int(np.flatnonzero(odd)[0]), "not candidate or interpolated")
    if "triangle" in raw:
        cols["triangle"] = ints("triangle")
    if all(c in raw for c in ("v1", "v2", "v3")):
        vert = np.column_stack([ints(c) for c in ("v1", "v2", "v3")]).reshape(n, 3)
        out = (vert < -1) | (vert >= n)
        if out.any():
            i, k = (int(a[0]) for a in np.nonzero(out))
            raise bad(f"v{k + 1}", i, f"not a row of this file (0..{n - 1})")
        cols["vertices"] = vert
    if all(c in raw for c in ("w1", "w2", "w3")):
        cols["weights"] = np.column_stack([floats(c) for c in ("w1", "w2", "w3")]).reshape(n, 3)
    if "reachable" in raw:
        cols["reachable"] = _switches(path, raw["reachable"], "reachable", lines)
    if "reason" in raw:
        cols["reason"] = raw["reason"].astype(str)
    for name in ("pos_err", "rot_err", "manipulability"):
        if name in raw:
            cols[name] = floats(name)
    qnames = [h for h in header if h[:1] == "q" and h[1:].isdigit()]
    if qnames:
        cols["q"] = np.column_stack([floats(c) for c in qnames]).reshape(n, len(qnames))
        if "reachable" in cols:  # a reachable grasp has its joint solution
            odd = cols["reachable"] & ~np.isfinite(cols["q"]).all(axis=1)
            if odd.any():
                i = int(np.flatnonzero(odd)[0])
                k = int(np.flatnonzero(~np.isfinite(cols["q"][i]))[0])
                raise bad(qnames[k], i, "a reachable grasp needs a finite joint value")
    for name in header:
        if name in CSV_COLUMNS or name in qnames or name in cols:
            continue
        cols[name] = _parse_column(raw[name])
    return GraspTable(cols)


def check_csv_cells(path: Path, line: int, header: list[str] | None, row: list[str]) -> None:
    """Refuse a CSV row with a cell longer than :data:`~gcm_pipeline.limits.MAX_CSV_CELL`.

    Raises:
        InputError: Names the line, the column and the cell's length
            (attributes ``path``, ``row``: the line, ``key``, ``value``: the length).
    """
    if max(map(len, row), default=0) <= MAX_CSV_CELL:
        return
    k = max(range(len(row)), key=lambda j: len(row[j]))
    name = clip(header[k], 40) if header is not None and k < len(header) else f"#{k + 1}"
    err = InputError(
        f"{path}:{line}: column {name}: a cell of {len(row[k]):,} characters; a CSV cell "
        f"holds at most {MAX_CSV_CELL} (gcm_pipeline.limits.MAX_CSV_CELL)"
    )
    err.path, err.row, err.key, err.value = path, line, name, len(row[k])  # type: ignore[attr-defined]
    raise err


def _switches(path: Path, text: np.ndarray, name: str, lines: list[int]) -> np.ndarray:
    odd = ~np.isin(text, ("true", "false"))
    if odd.any():
        i = int(np.flatnonzero(odd)[0])
        raise InputError(
            f"{path}:{lines[i]}: column {name!r}: not true or false: {clip(str(text[i]))}"
        )
    return np.asarray(text == "true", dtype=bool)


def _parse_column(values: Any) -> np.ndarray:
    """A further column read back: bool, int, float (empty = NaN) or, failing those, str."""
    text = np.array(values, dtype=str).reshape(-1)
    if text.size and all(v in ("true", "false") for v in text.tolist()):
        return text == "true"
    if text.size and all(re.fullmatch(r"-?[0-9]{1,18}", v) for v in text.tolist()):
        return text.astype(np.int64)
    floats = np.where(text == "", "nan", text)
    try:
        return floats.astype(float)
    except ValueError:
        return text


# ------------------------------------------------------------ .npy / .npz, checked

#: Most header bytes of one .npy array (NumPy's own default bound).
_MAX_NPY_HEADER = 10_000


def npy_header(
    path: Path, fh: Any, what: str, available: int
) -> tuple[tuple[int, ...], np.dtype[Any]]:
    """Shape and dtype of the .npy array at ``fh``; refuses a header that promises too much.

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
            shape, _, dtype = np.lib.format.read_array_header_1_0(fh, _MAX_NPY_HEADER)
        else:
            shape, _, dtype = np.lib.format.read_array_header_2_0(fh, _MAX_NPY_HEADER)
    except Exception as exc:  # the header is parsed as Python literals: anything can go wrong
        raise InputError(f"{path}: {what} is not a .npy array: {clip(str(exc))}") from None
    if dtype.hasobject:
        raise InputError(
            f"{path}: {what} holds Python objects (a pickle); only plain arrays are read"
        )
    need = fh.tell() + int(np.prod(shape, dtype=object)) * dtype.itemsize
    if need > available:
        raise InputError(
            f"{path}: {what} is truncated or corrupt: its header says shape {shape} "
            f"({need:,} bytes) but there are {available:,}"
        )
    return tuple(int(k) for k in shape), dtype


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
            raise InputError(f"{path}: it is {what}; a regular file is needed")
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
                        "holds arrays only"
                    )
                infos[info.filename[: -len(".npy")]] = info
            total = sum(info.file_size for info in infos.values())
            if total > max_bytes:
                raise InputError(
                    f"{path}: its arrays take {total:,} bytes, more than the {max_bytes:,} "
                    "read here"
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
    except (
        zipfile.BadZipFile,
        zipfile.LargeZipFile,
        zlib.error,
        OSError,
        EOFError,
        ValueError,
    ) as exc:
        raise InputError(f"{path}: not a readable .npz archive: {clip(str(exc))}") from None
    except NotImplementedError as exc:  # a compression method zipfile lacks
        raise InputError(f"{path}: not a readable .npz archive: {exc}") from None
    return arrays


# ------------------------------------------------------------ manifold.npz


def _manifold_arrays(manifold: Manifold) -> dict[str, Any]:
    """Every field of the manifold as an array (None fields left out)."""
    arrays: dict[str, Any] = {}
    for f in dataclasses.fields(manifold):
        value = getattr(manifold, f.name)
        if value is None:
            continue
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
    """Read ``manifold.npz`` back into a :class:`~gcm_pipeline.stages.manifold.Manifold`.

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
        raise InputError(f"{path}: missing array(s) {', '.join(missing)}")

    def fail(name: str, what: str) -> InputError:
        return InputError(f"{path}: array {name!r} {what}")

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


def write_run_files(
    out_dir: str | Path, grasps: GraspTable, manifold: Manifold, config: Mapping[str, Any]
) -> None:
    """Write ``grasps.csv``, ``manifold.npz`` (vertex ids = csv rows) and ``config.yaml``."""
    out = Path(out_dir)
    order = write_grasps_csv(grasps, out / "grasps.csv")
    csv_row = np.empty(len(order), dtype=np.int64)
    csv_row[order] = np.arange(len(order))
    write_manifold(manifold, out / "manifold.npz", csv_rows=csv_row[: len(manifold.chart)])
    write_configurations(grasps, out / "configurations.npz", order)
    if "solutions" in grasps:
        write_solutions(grasps, out / "solutions.npz", order)
    write_config(config, out / "config.yaml")


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


# ------------------------------------------------------------ json / yaml


def _json_clean(value: Any) -> Any:
    """NumPy scalars/arrays to Python, NaN/inf to None, paths to str."""
    if isinstance(value, Mapping):
        return {str(k): _json_clean(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_json_clean(v) for v in value]
    if isinstance(value, np.ndarray):
        return _json_clean(value.tolist())
    if isinstance(value, np.generic):
        return _json_clean(value.item())
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if isinstance(value, Path):
        return str(value)
    return value


def versions() -> dict[str, str]:
    """Versions of Python and the main packages, for ``summary.json``."""
    out = {"python": platform.python_version()}
    for name, module in (
        ("gcm_pipeline", "gcm_pipeline"),
        ("numpy", "numpy"),
        ("scipy", "scipy"),
        ("pinocchio", "pinocchio"),
        ("pydantic", "pydantic"),
    ):
        try:
            out[name] = str(__import__(module).__version__)
        except (ImportError, AttributeError):
            continue
    return out


def write_summary(summary: Mapping[str, Any], path: str | Path) -> None:
    """Write ``summary.json`` (NaN becomes null; keys in the given order)."""
    text = json.dumps(_json_clean(summary), indent=2, allow_nan=False)
    Path(path).write_text(text + "\n", encoding="utf-8")


def write_config(config: Mapping[str, Any], path: str | Path) -> None:
    """Write the resolved config as YAML (section order kept)."""
    text = yaml.safe_dump(_json_clean(config), sort_keys=False, default_flow_style=None)
    Path(path).write_text(text, encoding="utf-8")


# ------------------------------------------------------------ read_run


class RunData(NamedTuple):
    """A run directory read back by :func:`read_run`.

    Attributes:
        grasps: The grasp table: candidates first, in manifold vertex order,
            then the other rows in file order (ranked first).
        manifold: The manifold (triangles index the candidate rows).
        summary: ``summary.json`` as a dict.
        run_dir: The run directory.
    """

    grasps: GraspTable
    manifold: Manifold
    summary: dict[str, Any]
    run_dir: Path


def read_run(run_dir: str | Path) -> RunData:
    """Read a run directory written by ``gcm run`` / :meth:`Pipeline.run`.

    Args:
        run_dir: The run directory.

    Returns:
        The grasp table (``dq`` rebuilt from x..qz), the manifold and the
        summary. The table's rows are ordered as in the run: the candidates
        first, in manifold vertex order (so the manifold's triangles and the
        ``vertices`` column index them), then the other rows in file order
        (ranked first).

    Raises:
        InputError: Not a run directory, or a file in it cannot be read or
            does not match the others (names the file and what is wrong).
    """
    run_dir = Path(run_dir)
    if not run_dir.is_dir():
        if run_dir.exists():
            raise InputError(f"not a run directory: {run_dir} is a file (give its folder)")
        raise InputError(f"run directory not found: {run_dir}")
    missing = [
        f for f in ("grasps.csv", "summary.json", "manifold.npz") if not (run_dir / f).is_file()
    ]
    if missing:
        raise InputError(f"not a run directory: {run_dir} lacks {', '.join(missing)}")
    summary = read_summary(run_dir / "summary.json")
    grasps = read_grasps_csv(run_dir / "grasps.csv")
    manifold = read_manifold(run_dir / "manifold.npz", n_rows=len(grasps))
    vertex_rows = manifold_vertex_rows(run_dir / "manifold.npz", len(manifold.chart))
    if "vertices" in grasps and len(grasps):
        used = np.asarray(grasps["vertices"])
        used = np.unique(used[used >= 0])
        stray = np.setdiff1d(used, vertex_rows)
        if stray.size:
            raise InputError(
                f"{run_dir / 'grasps.csv'}: v1..v3 name row {int(stray[0])}, which is not a "
                "candidate of manifold.npz"
            )
    rest = np.setdiff1d(np.arange(len(grasps)), vertex_rows, assume_unique=False)
    perm = np.concatenate([vertex_rows, rest])
    grasps = grasps.take(perm)
    if "vertices" in grasps:  # rows of the file -> rows of the reordered table
        new_row = np.empty(len(perm), dtype=np.int64)
        new_row[perm] = np.arange(len(perm))
        vert = np.asarray(grasps["vertices"])
        grasps = grasps.with_columns(vertices=np.where(vert >= 0, new_row[np.maximum(vert, 0)], -1))
    return RunData(grasps, manifold, summary, run_dir)


def read_summary(path: str | Path) -> dict[str, Any]:
    """Read and check a run's ``summary.json``.

    ``counts`` (when present) maps names to counts or to ``{reason: count}``
    breakdowns; ``ranking`` (when present) has a text ``metric`` and a list
    ``top``.

    Raises:
        InputError: Unreadable, not JSON, not an object, or a part of the
            wrong type (names it).
    """
    path = Path(path)
    try:
        with path.open("rb") as fh:
            data = fh.read(_MAX_SUMMARY_BYTES + 1)
    except OSError as exc:
        raise InputError(f"{path}: cannot read: {exc.strerror or exc}") from None
    if len(data) > _MAX_SUMMARY_BYTES:
        raise InputError(f"{path}: larger than {_MAX_SUMMARY_BYTES >> 20} MiB; not a summary")
    try:
        summary = json.loads(data.decode("utf-8"))
    except (ValueError, RecursionError) as exc:
        raise InputError(f"{path}: not valid JSON: {clip(str(exc))}") from None
    if not isinstance(summary, dict):
        raise InputError(f"{path}: expected a JSON object, got {type(summary).__name__}")
    counts = summary.get("counts", {})
    if not isinstance(counts, dict):
        raise InputError(f"{path}: 'counts' must be an object, got {type(counts).__name__}")
    for key, value in counts.items():
        ok = (isinstance(value, int) and not isinstance(value, bool)) or (
            isinstance(value, dict)
            and all(isinstance(v, int) and not isinstance(v, bool) for v in value.values())
        )
        if not ok:
            raise InputError(f"{path}: counts.{str(key)[:60]} must be a count, got {clip(value)}")
    ranking = summary.get("ranking", {})
    if not isinstance(ranking, dict):
        raise InputError(f"{path}: 'ranking' must be an object, got {type(ranking).__name__}")
    if not isinstance(ranking.get("metric", ""), str):
        raise InputError(f"{path}: ranking.metric must be a text, got {clip(ranking['metric'])}")
    if not isinstance(ranking.get("top", []), list):
        raise InputError(f"{path}: ranking.top must be a list")
    return summary
