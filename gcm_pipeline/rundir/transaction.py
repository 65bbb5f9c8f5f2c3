"""The run directory as a transaction: written to a temporary sibling, renamed when complete.

Everything is written into a temporary sibling directory
(``.<name>.tmp-<pid>-<random>``, marker first) that is renamed to the final
name only when complete (:func:`atomic_dir`); on any failure, Ctrl-C
included, the temporary directory is removed, so a directory named like the
run is always complete. With ``force`` an existing run is replaced only at
that final rename, with the parent directory locked (concurrent runs into
one place take turns) and signals held until the swap is done. The same
machinery serves other directory kinds (``atomic_dir(path, kind="study")``).

``.gcm.json`` is the marker that says gcm_pipeline wrote the directory
(:func:`write_marker`); only a directory with a valid marker is ever
replaced, whatever other files it holds.

A single file is replaced the same way (:func:`atomic_file`): written to a
temporary sibling, renamed over the old one when complete. Every file the
package writes in place (exports, the study's tables, the mesh cache) goes
through it.
"""

from __future__ import annotations

import contextlib
import errno
import json
import logging
import os
import re
import shutil
import sys
import tempfile
import time
import uuid
from collections.abc import Iterable, Iterator
from pathlib import Path
from typing import Any

from gcm_pipeline import __version__, interrupts
from gcm_pipeline.errors import OutputError, clip

__all__ = [
    "MARKER",
    "atomic_dir",
    "atomic_file",
    "atomic_run_dir",
    "check_output_dir",
    "disk_full",
    "is_project_dir",
    "looks_like_run_dir",
    "read_marker",
    "write_marker",
]

log = logging.getLogger(__name__)


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
                f"refusing to replace {out}: it is a gcm {other[:40]} directory, not "
                f"{'an' if kind[:1] in 'aeiou' else 'a'} {kind} directory; choose another --out"
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
            with interrupts.deferred():
                _replace_dir(tmp, out, force=force, keep=keep, kind=kind)
                _remove_stale(out)
    except BaseException as exc:
        with interrupts.deferred():
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


@contextlib.contextmanager
def atomic_file(path: str | Path) -> Iterator[Path]:
    """Yield a temporary sibling file that replaces ``path`` when the block succeeds.

    The one way this package replaces a file: the block writes the temporary
    file ``.<name>.<random>.tmp`` beside ``path``; on a clean exit it gets mode
    0644 (less the umask) and is renamed over ``path``, so a reader sees the
    old file or the new one, never half of one. On any exception, Ctrl-C
    included, it is removed and the exception propagates (``path`` is left as
    it was).

    Raises:
        OutputError: The temporary file cannot be created (names ``path``), or
            ``path`` became a directory meanwhile.
    """
    path = Path(path)
    try:
        fd, name = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    except OSError as exc:
        raise OutputError(f"cannot write {path}: {exc.strerror or exc}") from None
    os.close(fd)
    tmp = Path(name)
    try:
        yield tmp
        os.chmod(tmp, 0o644 & ~_umask())
        try:
            os.replace(tmp, path)
        except IsADirectoryError:  # made meanwhile (else refused before any work)
            raise OutputError(f"cannot write {path}: it is a directory; remove it") from None
    except BaseException:
        with contextlib.suppress(OSError):
            tmp.unlink()
        raise


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
