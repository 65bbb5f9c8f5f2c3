"""The study directory: one file per finished placement, consolidated outputs, resume.

Layout::

    .gcm.json           the project's marker (kind ``study``, :mod:`gcm_pipeline.rundir`)
    .study.lock         held (``flock``) by the study running here: a second study
                        into the same directory stops with an error instead of
                        writing over the first one's files
    study.json          what study this is (its key, the study file, the base config);
                        written first, checked on every rerun
    placements/000042.npz
                        one finished placement (row + grasp arrays, and for the
                        report each grasp's reason code and the best grasp's q),
                        written atomically
    placements.csv      one row per finished placement, by id
    reachability.npz    placements x grasps: reachable, metric, manipulability
    summary.json        best placement, counts, engine, workers, timings, versions
    coverage.png        coverage heat map over the x-y grid
    best/               the full run directory of the best placement (gcm run)
    study.html          the report: coverage maps, placements table, a placement's
                        3-D scene (:mod:`gcm_pipeline.study.report`)

Every file is written to a temporary name in its folder and renamed, so a
killed study leaves only complete files; ``placements/`` is the record a
rerun resumes from (finished placements are never recomputed).
``placements.csv`` and ``summary.json`` are rewritten every few seconds while
the study runs.
"""

from __future__ import annotations

import contextlib
import csv
import io as _io
import json
import logging
import os
import stat
from collections.abc import Callable, Iterable, Iterator, Mapping
from pathlib import Path
from typing import Any

import numpy as np

from gcm_pipeline.config.study import AXES
from gcm_pipeline.errors import InputError, OutputError, clip
from gcm_pipeline.rundir import arrays, transaction
from gcm_pipeline.rundir.grasps_csv import format_floats
from gcm_pipeline.rundir.run import json_clean

try:
    import fcntl
except ImportError:  # pragma: no cover - not POSIX
    fcntl = None  # type: ignore[assignment]

__all__ = [
    "CSV_COLUMNS",
    "MAX_META_BYTES",
    "POSE_COLUMNS",
    "StudyDir",
    "atomic_write",
    "read_part",
]

log = logging.getLogger(__name__)

#: Pose columns of ``placements.csv``: ``<object|base>_<x|y|z|yaw_deg>``.
POSE_COLUMNS = tuple(f"{pose}_{key}" for pose in ("object", "base") for key in AXES)

#: The numbers a placement's run reports (null allowed: NaN, or a failed placement).
_RESULTS = (
    "candidates",
    "densified",
    "reachable",
    "coverage",
    "candidates_reachable",
    "best_metric",
    "mean_metric",
    "best_manipulability",
    "mean_manipulability",
    "time_s",
)

#: Columns of ``placements.csv``, in order.
CSV_COLUMNS = ("id", "round", "object", *POSE_COLUMNS, *_RESULTS, "node", "error", "overrides")

#: Per-grasp arrays of a placement part.
ARRAYS = ("reachable_mask", "metric", "manipulability", "pose", "pose_object", "is_candidate")

#: Arrays a part may add for the study report (older parts lack them): per-grasp
#: ``reason_code`` (uint8, 0 reachable, k the k-th of ``reason_names``) and ``q_best``.
REPORT_ARRAYS = ("reason_code", "reason_names", "q_best")

#: Numeric fields of a placement's row.
_NUMBERS = (*_RESULTS, *POSE_COLUMNS)

_LOCK = ".study.lock"

#: The files a study writes at the top of its directory.
OUTPUT_FILES = (
    "study.json",
    "placements.csv",
    "reachability.npz",
    "summary.json",
    "coverage.png",
    "study.html",
)

#: Most bytes of ``study.json`` (a study writes its study file and base config there: kB).
MAX_META_BYTES = 16 * 1024**2

#: Most bytes a placement part's arrays may take (the densify limit's poses, with room).
_MAX_PART_BYTES = 1 << 30


@contextlib.contextmanager
def atomic_write(path: Path) -> Iterator[Path]:
    """Yield a temporary path beside ``path`` that replaces ``path`` on success.

    :func:`~gcm_pipeline.rundir.transaction.atomic_file`; on any exception the
    temporary file is removed and ``path`` is left as it was (a full file
    system is an :class:`OutputError` naming ``path``).
    """
    try:
        with transaction.atomic_file(path) as tmp:
            yield tmp
    except BaseException as exc:
        full = transaction.disk_full(
            path, exc, "the finished placements are kept (a rerun resumes)"
        )
        if full is not None:
            raise full from None
        raise


def _write_text(path: Path, text: str) -> None:
    with atomic_write(path) as tmp:
        tmp.write_text(text, encoding="utf-8")


class StudyDir:
    """A study directory (see the module docstring).

    Args:
        path: The directory.
    """

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path).expanduser().absolute()
        self.parts = self.path / "placements"

    def __repr__(self) -> str:
        return f"StudyDir({str(self.path)!r})"

    # --- identity -------------------------------------------------------------------

    def check(self, key: str, *, keep: Iterable[str | Path] = ()) -> bool:
        """Check that the study ``key`` may be written here; nothing is written.

        Args:
            key: The study's key (:meth:`StudyPlan.key`).
            keep: Input files that must not lie inside the directory.

        Returns:
            True when the directory holds this study already (a resume).

        Raises:
            OutputError: The path is a file or a symbolic link; the directory is
                not empty and not a study directory (no ``.gcm.json`` marker of
                kind ``study``), or holds another study; it is the working
                directory or one of its parents; it holds an input.
        """
        out = self.path
        try:
            used = out.is_dir() and not out.is_symlink()
            names = {p.name for p in out.iterdir()} if used else set()
        except OSError as exc:
            raise OutputError(f"cannot read study directory {out}: {exc}") from None
        if names and names <= {_LOCK}:
            return False  # left by a study stopped before it wrote anything
        # an existing study directory is continued, never replaced: "force" only
        # lets the transaction's checks accept a directory that carries the study marker
        transaction.check_output_dir(out, force=bool(names), keep=keep, kind="study")
        self._check_slots(names)
        return bool(names) and self.holds(key)

    def _check_slots(self, names: set[str]) -> None:
        """Refuse a directory, pipe or device where the study writes a file, a file for a folder.

        Found before any work: a ``placements.csv`` that is a directory made the
        study end in a traceback when it wrote its tables.
        """
        for name in sorted(names & (set(OUTPUT_FILES) | {"placements"})):
            try:
                mode = os.lstat(self.path / name).st_mode
            except OSError:
                continue
            want_dir = name == "placements"
            if stat.S_ISLNK(mode) and not want_dir:
                continue  # a rename replaces the link itself
            if want_dir and not stat.S_ISDIR(mode):
                raise OutputError(
                    f"{self.path / name} is not a directory; the study keeps its finished "
                    "placements there (remove it or choose another --out)"
                )
            if not want_dir and not stat.S_ISREG(mode):
                what = "a directory" if stat.S_ISDIR(mode) else "not a regular file"
                raise OutputError(
                    f"{self.path / name} is {what}; the study writes its {name} there "
                    "(remove it or choose another --out)"
                )

    def holds(self, key: str) -> bool:
        """Whether the directory holds the study ``key`` already (checked again under :meth:`lock`).

        Raises:
            OutputError: It holds another study.
        """
        out = self.path
        if not (out / transaction.MARKER).exists():
            return False
        meta = self.read_meta()
        if meta is None or meta.get("key") != key:
            source = (meta or {}).get("source") or "an unknown study"
            raise OutputError(
                f"{out} holds a different study (from {source}, key "
                f"{(meta or {}).get('key')}, this one {key}); choose another --out or remove it"
            )
        return True

    @contextlib.contextmanager
    def lock(self) -> Iterator[None]:
        """Hold the directory for this process while the block runs (``.study.lock``).

        Creates the directory when needed. A directory this call created is
        removed again when the block fails before anything else was written
        into it.

        Raises:
            OutputError: Another process holds it (a study running into the same
                directory), or it cannot be created.
        """
        made = not self.path.exists()
        lock = self.path / _LOCK
        try:
            self.path.mkdir(parents=True, exist_ok=True)
            # never through a symbolic link (its target would be overwritten), never a pipe
            fd = os.open(
                lock,
                os.O_RDWR | os.O_CREAT | getattr(os, "O_NOFOLLOW", 0) | os.O_NONBLOCK,
                0o644,
            )
        except OSError as exc:
            what = "is not a regular file" if lock.is_symlink() or lock.is_dir() else exc
            raise OutputError(f"cannot lock study directory {self.path}: {lock} {what}") from None
        if not stat.S_ISREG(os.fstat(fd).st_mode):
            os.close(fd)
            raise OutputError(
                f"cannot lock study directory {self.path}: {lock} is not a regular file"
            )
        try:
            if fcntl is not None:
                try:
                    fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
                except BlockingIOError:
                    holder = os.pread(fd, 32, 0).decode("ascii", "replace").strip()
                    who = f" (pid {holder})" if holder.isdigit() else ""
                    raise OutputError(
                        f"{self.path} is in use by another gcm study{who}; wait for it to "
                        "finish or choose another --out"
                    ) from None
                except OSError:  # pragma: no cover - a filesystem without locks
                    pass
            os.ftruncate(fd, 0)
            os.pwrite(fd, f"{os.getpid()}\n".encode(), 0)
            try:
                yield
            except BaseException:
                if made:
                    self._remove_if_unused()
                raise
        finally:
            os.close(fd)  # releases the lock

    def _remove_if_unused(self) -> None:
        """Remove the directory when it holds nothing but the lock (and empty ``placements/``)."""
        with contextlib.suppress(OSError):
            names = {p.name for p in self.path.iterdir()}
            if names <= {_LOCK, "placements"} and not any(self.parts.iterdir()):
                self.parts.rmdir()
        with contextlib.suppress(OSError):
            if {p.name for p in self.path.iterdir()} <= {_LOCK}:
                (self.path / _LOCK).unlink()
                self.path.rmdir()

    def read_meta(self) -> dict[str, Any] | None:
        """``study.json`` as a dict, or None when it is missing or not a study's.

        Raises:
            OutputError: It is not a regular file (a pipe would block), or it is
                larger than :data:`MAX_META_BYTES` (a study writes a few kB).
        """
        if not transaction.is_project_dir(self.path, "study"):
            return None
        path = self.path / "study.json"
        try:
            with arrays.open_regular(path) as fh:
                size = os.fstat(fh.fileno()).st_size
                if size > MAX_META_BYTES:
                    raise OutputError(
                        f"{path} is {size:,} bytes, more than the {MAX_META_BYTES:,} a study's "
                        "study.json may hold; it is not what a study wrote (remove the "
                        "directory or choose another --out)"
                    )
                raw = fh.read(MAX_META_BYTES + 1)
            meta = json.loads(raw.decode("utf-8"))
        except InputError as exc:  # a directory, a pipe, a device
            raise OutputError(str(exc)) from None
        except (OSError, ValueError):
            return None
        return meta if isinstance(meta, dict) else None

    def create(self, meta: Mapping[str, Any]) -> None:
        """Create the directory, its ``.gcm.json`` marker and ``study.json`` (kept when there)."""
        try:
            self.parts.mkdir(parents=True, exist_ok=True)
            if transaction.read_marker(self.path) is None:
                transaction.write_marker(self.path, "study")
        except OSError as exc:
            raise OutputError(f"cannot create study directory {self.path}: {exc}") from None
        if self.read_meta() is None:
            text = json.dumps(json_clean(dict(meta)), indent=2) + "\n"
            if len(text.encode("utf-8")) > MAX_META_BYTES:  # it could not be read back
                raise OutputError(
                    f"{self.path / 'study.json'}: the study file and base config take "
                    f"{len(text.encode('utf-8')):,} bytes, more than {MAX_META_BYTES:,}"
                )
            _write_text(self.path / "study.json", text)

    # --- placements -------------------------------------------------------------------

    def part_path(self, pid: int) -> Path:
        """The file of placement ``pid``."""
        return self.parts / f"{pid:06d}.npz"

    def write_part(self, row: Mapping[str, Any], arrays: Mapping[str, np.ndarray]) -> None:
        """Write one finished placement (its row and grasp arrays) atomically."""
        payload: dict[str, Any] = {k: np.asarray(v) for k, v in arrays.items()}
        payload["row"] = np.array(json.dumps(json_clean(dict(row))))
        with atomic_write(self.part_path(int(row["id"]))) as tmp:
            with open(tmp, "wb") as f:
                np.savez(f, **payload)

    def finished_ids(self) -> set[int]:
        """Ids of the placements with a part file (not read: see :meth:`load_parts`)."""
        if not self.parts.is_dir():
            return set()
        return {int(p.stem) for p in self.parts.glob("[0-9]*.npz") if p.stem.isdigit()}

    def load_parts(self) -> dict[int, dict[str, Any]]:
        """Every finished placement: id -> row (with its arrays under ``arrays``).

        A part that cannot be read or does not hold what a study writes (a
        damaged or edited file) is skipped with a warning: its placement runs
        again.
        """
        out: dict[int, dict[str, Any]] = {}
        if not self.parts.is_dir():
            return out
        for path in sorted(self.parts.glob("[0-9]*.npz")):
            if not path.stem.isdigit():
                continue
            try:
                row = read_part(path)
            except Exception as exc:  # a damaged file: run the placement again
                log.warning("study: ignoring %s, placement runs again (%s)", path, exc)
                continue
            out[int(row["id"])] = row
        return out

    # --- consolidated outputs ---------------------------------------------------------

    def write_csv(self, rows: Iterable[Mapping[str, Any]]) -> Path:
        """Write ``placements.csv`` (rows sorted by id; floats round-trip, NaN empty)."""
        buf = _io.StringIO()
        writer = csv.writer(buf, lineterminator="\n")
        writer.writerow(CSV_COLUMNS)
        for row in sorted(rows, key=lambda r: int(r["id"])):
            writer.writerow([_cell(row.get(c)) for c in CSV_COLUMNS])
        path = self.path / "placements.csv"
        _write_text(path, buf.getvalue())
        return path

    def write_json(self, name: str, data: Mapping[str, Any]) -> Path:
        """Write ``name`` (e.g. ``summary.json``) atomically; NaN becomes null."""
        path = self.path / name
        _write_text(path, json.dumps(json_clean(dict(data)), indent=2, allow_nan=False) + "\n")
        return path

    def write_npz(self, name: str, arrays: Mapping[str, np.ndarray]) -> Path:
        """Write a compressed ``.npz`` atomically."""
        path = self.path / name
        with atomic_write(path) as tmp:
            with open(tmp, "wb") as f:
                packed: dict[str, Any] = {k: np.asarray(v) for k, v in arrays.items()}
                np.savez_compressed(f, **packed)
        return path

    def write_with(self, name: str, writer: Callable[[Path], None]) -> Path:
        """Write ``name`` by ``writer(tmp_path)`` atomically (e.g. a PNG)."""
        path = self.path / name
        with atomic_write(path) as tmp:
            writer(tmp)
        return path


def read_part(path: Path) -> dict[str, Any]:
    """One placement part: its row with its arrays under ``arrays``.

    Raises:
        Exception: The file cannot be read or does not hold what
            :meth:`StudyDir.write_part` writes (the message says what).
    """
    # sizes from the headers first: a compressed member may unpack to gigabytes
    data = arrays.read_npz(path, max_bytes=_MAX_PART_BYTES)
    if "row" not in data:
        raise ValueError("it has no row")
    row = json.loads(str(data.pop("row")))
    if not isinstance(row, dict):
        raise ValueError("its row is not a JSON object")
    row["arrays"] = data
    _check_part(int(path.stem), row)
    return row


def _check_part(pid: int, row: Mapping[str, Any]) -> None:
    """Raise ValueError unless ``row`` is a part as :meth:`StudyDir.write_part` writes one."""
    if type(row.get("id")) is not int or row["id"] != pid:
        raise ValueError(f"its id {row.get('id')!r} is not its file name's {pid}")
    if not isinstance(row.get("object"), str) or not isinstance(row.get("error", ""), str):
        raise ValueError("object or error is not a string")
    if type(row.get("round")) is not int or row["round"] < 0:
        raise ValueError(f"round {row.get('round')!r} is not a whole number >= 0")
    overrides = row.get("overrides")
    if not isinstance(overrides, list) or not all(isinstance(o, str) for o in overrides):
        raise ValueError(f"overrides {clip(repr(overrides))} is not a list of KEY=VALUE strings")
    for key in _NUMBERS:
        value = row.get(key)
        if value is not None and (isinstance(value, bool) or not isinstance(value, (int, float))):
            raise ValueError(f"{key} is not a number: {value!r}")
    arrays = row["arrays"]
    if row.get("error"):
        return
    if row.get("coverage") is None or not set(ARRAYS) <= set(arrays) <= {*ARRAYS, *REPORT_ARRAYS}:
        raise ValueError(f"a finished placement needs coverage and the arrays {', '.join(ARRAYS)}")
    full, arrays = arrays, {k: v for k, v in arrays.items() if k in ARRAYS}
    if not 0.0 <= row["coverage"] <= 1.0:
        raise ValueError(f"coverage {row['coverage']!r} is not within [0, 1]")
    lengths = {k: (v.shape[0] if v.ndim else None) for k, v in arrays.items()}
    if len(set(lengths.values())) != 1:
        raise ValueError(
            "arrays of different lengths: " + ", ".join(f"{k} {v}" for k, v in lengths.items())
        )
    n = arrays["reachable_mask"].shape[:1]
    shapes = {
        "reachable_mask": (n, "b"),
        "is_candidate": (n, "b"),
        "metric": (n, "f"),
        "manipulability": (n, "f"),
        "pose": ((*n, 7), "f"),
        "pose_object": ((*n, 7), "f"),
    }
    for key, value in arrays.items():
        shape, kind = shapes[key]
        if value.shape != shape or value.dtype.kind != kind:
            raise ValueError(f"{key} has shape {value.shape} and dtype {value.dtype}")
    reached = int(np.count_nonzero(arrays["reachable_mask"]))
    total = arrays["reachable_mask"].shape[0]
    if row.get("reachable") != reached or row.get("densified") != total:
        raise ValueError(
            f"reachable {row.get('reachable')!r} of {row.get('densified')!r} is not its "
            f"mask's {reached} of {total}"
        )
    if total and abs(row["coverage"] - reached / total) > 1e-12:
        raise ValueError(f"coverage {row['coverage']!r} is not {reached} / {total}")
    _check_report_arrays(full)


def _check_report_arrays(arrays: Mapping[str, np.ndarray]) -> None:
    """Raise ValueError unless the report's optional arrays agree with the mask."""
    if "reason_code" in arrays:
        code, names = arrays["reason_code"], arrays.get("reason_names", np.empty(0, str))
        mask = arrays["reachable_mask"]
        if code.dtype != np.uint8 or code.shape != mask.shape or names.dtype.kind != "U":
            raise ValueError(f"reason_code has shape {code.shape} and dtype {code.dtype}")
        if np.any((code == 0) != mask) or int(code.max(initial=0)) > names.shape[0]:
            raise ValueError("reason_code does not agree with reachable_mask and reason_names")
    q = arrays.get("q_best")
    if q is not None and (q.ndim != 1 or q.dtype.kind != "f"):
        raise ValueError(f"q_best has shape {q.shape} and dtype {q.dtype}")


def _cell(value: Any) -> str:
    if value is None:
        return ""
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, (float, np.floating)):
        return format_floats(np.array([value]))[0]
    if isinstance(value, (list, tuple)):
        return json.dumps(list(value))
    return str(value)
