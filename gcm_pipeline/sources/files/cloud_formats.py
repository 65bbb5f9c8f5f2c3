"""Readers of scene-cloud files, chunk by chunk: ``.ply``, ``.pcd``, ``.png``, ``.npy`` rows.

The pieces :mod:`gcm_pipeline.sources.clouds` builds its formats from: a
:class:`Chunk` of points in the file's frame, rows of a ``.npy`` array read block
by block (:class:`Rows`, a file or an ``.npz`` member), PCL's ``.pcd``
(``DATA ascii`` and ``binary``), ``.ply`` through trimesh and single-channel
``.png`` images (depth, labels) through Pillow.
"""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import trimesh
from PIL import Image

from gcm_pipeline.bounds import CLOUD_CHUNK, MAX_CLOUD_FILE_BYTES
from gcm_pipeline.errors import InputError, clip
from gcm_pipeline.rundir.arrays import npy_layout, open_regular

__all__ = [
    "MAX_PNG_PIXELS",
    "Chunk",
    "MemRows",
    "Rows",
    "as_colors",
    "check_whole",
    "pcd_chunks",
    "ply_chunks",
    "read_png",
]

#: Most pixels of a ``.png`` depth image or segmentation (decoded whole).
MAX_PNG_PIXELS = 50_000_000


class Chunk:
    """Points (M, 3) in the file's frame with optional segments (M,) and colours (M, 3)."""

    __slots__ = ("colors", "points", "segments")

    def __init__(
        self, points: np.ndarray, segments: np.ndarray | None, colors: np.ndarray | None
    ) -> None:
        self.points, self.segments, self.colors = points, segments, colors

    def take(self, keep: np.ndarray) -> Chunk:
        """The rows ``keep`` (a mask or indices)."""
        return Chunk(
            self.points[keep],
            None if self.segments is None else self.segments[keep],
            None if self.colors is None else self.colors[keep],
        )


class Rows:
    """Rows of one .npy array (a file or an .npz member), read in order, block by block."""

    def __init__(self, path: Path, fh: Any, available: int, what: str) -> None:
        self.path, self.fh, self.what = path, fh, what
        shape, fortran, dtype = npy_layout(path, fh, what, available)  # size checked there
        if fortran and len(shape) > 1:
            raise InputError(f"{path}: {what} is stored in Fortran order; save it in C order")
        if not np.issubdtype(dtype, np.number):
            raise InputError(f"{path}: {what} has dtype {dtype}; numbers are needed", path=path)
        self.shape, self.dtype = shape, dtype
        self.row_items = int(np.prod(self.shape[1:], dtype=np.int64)) if len(shape) > 1 else 1

    def read(self, rows: int) -> np.ndarray:
        """The next ``rows`` rows."""
        n = rows * self.row_items
        data = self.fh.read(n * self.dtype.itemsize)
        if len(data) != n * self.dtype.itemsize:
            raise InputError(f"{self.path}: {self.what} is truncated", path=self.path)
        return np.frombuffer(data, dtype=self.dtype).reshape(rows, *self.shape[1:])


class MemRows:
    """An in-memory array with the :class:`Rows` interface."""

    def __init__(self, arr: np.ndarray) -> None:
        self.arr, self.shape, self.dtype, self.at = arr, arr.shape, arr.dtype, 0

    def read(self, rows: int) -> np.ndarray:
        """The next ``rows`` rows (a 0-d array: its one value)."""
        out = self.arr.reshape(-1)[self.at : self.at + rows] if self.arr.ndim == 0 else None
        out = self.arr[self.at : self.at + rows] if out is None else out
        self.at += rows
        return out


def as_colors(c: np.ndarray) -> np.ndarray:
    """Colours (M, 3) as uint8 (floats in [0, 1] scaled to 255)."""
    c = np.asarray(c)
    if np.issubdtype(c.dtype, np.floating) and c.size and np.nanmax(c) <= 1.0:
        c = c * 255.0
    return np.clip(np.nan_to_num(c), 0, 255).astype(np.uint8)


def read_png(path: Path, where: str) -> np.ndarray:
    """A single-channel ``.png`` (a 16-bit depth image, a label image) as an (H, W) array."""
    check_whole(path, where)
    try:
        with Image.open(path) as img:
            w, h = img.size
            if w * h > MAX_PNG_PIXELS:
                raise InputError(
                    f"{where}: {path}: {w} x {h} pixels is above {MAX_PNG_PIXELS:,}", path=path
                )
            arr = np.asarray(img)
    except InputError:
        raise
    except (OSError, ValueError, Image.DecompressionBombError) as exc:
        raise InputError(f"{where}: {path}: not a readable .png: {clip(str(exc))}") from None
    if arr.ndim != 2:
        raise InputError(
            f"{where}: {path}: a depth or label .png has one channel, got shape {arr.shape}",
            path=path,
        )
    return arr


def ply_chunks(path: Path, where: str, counts: dict[str, int]) -> Iterator[Chunk]:
    """Vertices (and colours) of a ``.ply``, read whole by trimesh, in chunks."""
    check_whole(path, where)
    try:
        loaded = trimesh.load(str(path), process=False)
    except Exception as exc:  # trimesh raises many kinds on a bad file
        raise InputError(f"{where}: {path}: not a readable .ply: {clip(str(exc))}") from None
    pts = np.asarray(getattr(loaded, "vertices", np.zeros((0, 3))), dtype=np.float64)
    declared = _ply_vertices(path)
    if declared is not None and declared != len(pts):  # an ascii file cut short
        raise InputError(
            f"{where}: {path}: the PLY holds {len(pts):,} point{'s' if len(pts) != 1 else ''}, "
            f"its header says element vertex {declared}",
            path=path,
        )
    cols = getattr(loaded, "colors", None)
    if cols is None or len(cols) != len(pts):
        visual = getattr(loaded, "visual", None)
        cols = getattr(visual, "vertex_colors", None)
    cols = None if cols is None or len(cols) != len(pts) else np.asarray(cols)[:, :3]
    counts["read"] += len(pts)
    for a in range(0, len(pts), CLOUD_CHUNK):
        sl = slice(a, a + CLOUD_CHUNK)
        yield Chunk(pts[sl], None, None if cols is None else as_colors(cols[sl]))


def _ply_vertices(path: Path) -> int | None:
    """The vertex count a ``.ply`` header declares (``element vertex N``), or None."""
    with path.open("rb") as fh:
        head = fh.read(65536).split(b"end_header", 1)[0]
    for line in head.decode("ascii", "replace").splitlines():
        parts = line.split()
        if parts[:2] == ["element", "vertex"] and len(parts) == 3 and parts[2].isdigit():
            return int(parts[2])
    return None


def check_whole(path: Path, where: str) -> None:
    """Refuse a file read whole above ``MAX_CLOUD_FILE_BYTES``."""
    size = path.stat().st_size
    if size > MAX_CLOUD_FILE_BYTES:
        raise InputError(
            f"{where}: {path}: {size:,} bytes is above {MAX_CLOUD_FILE_BYTES:,} "
            f"(bounds.MAX_CLOUD_FILE_BYTES) for a {path.suffix} read whole; save the points "
            "as an (N, 3) .npy (read in chunks)",
            path=path,
        )


_PCD_TYPES = {
    ("F", 4): "f4",
    ("F", 8): "f8",
    ("U", 1): "u1",
    ("U", 2): "u2",
    ("U", 4): "u4",
    ("I", 1): "i1",
    ("I", 2): "i2",
    ("I", 4): "i4",
    ("U", 8): "u8",
    ("I", 8): "i8",
}


def pcd_chunks(path: Path, where: str, counts: dict[str, int]) -> Iterator[Chunk]:
    """Points (and colours) of a ``.pcd`` (``DATA ascii`` or ``binary``), in chunks."""
    with open_regular(path) as fh:
        head: dict[str, list[str]] = {}
        for _ in range(64):
            line = fh.readline(4096).decode("ascii", "replace").strip()
            if not line or line.startswith("#"):
                continue
            key, *vals = line.split()
            head[key.upper()] = vals
            if key.upper() == "DATA":
                break
        data = (head.get("DATA") or ["?"])[0].lower()
        if data == "binary_compressed":
            raise InputError(
                f"{where}: {path}: PCD 'DATA binary_compressed' is not read; convert it "
                "to binary or ascii (pcl_convert_pcd_ascii_binary in.pcd out.pcd 1)",
                path=path,
            )
        if data not in ("ascii", "binary") or "FIELDS" not in head:
            raise InputError(f"{where}: {path}: not a PCD file (no FIELDS/DATA header)")
        fields = head["FIELDS"]
        dtype, n = _pcd_dtype(head, fields, path, where)
        if not {"x", "y", "z"} <= set(fields):
            raise InputError(f"{where}: {path}: PCD fields {fields} lack x, y, z", path=path)
        has_rgb = "rgb" in fields or "rgba" in fields
        start = fh.tell()
        if data == "binary":
            size = path.stat().st_size
            if start + n * dtype.itemsize > size:
                raise InputError(f"{path}: PCD holds fewer than its {n:,} POINTS", path=path)
            for a in range(0, n, CLOUD_CHUNK):
                m = min(CLOUD_CHUNK, n - a)
                rec = np.frombuffer(fh.read(m * dtype.itemsize), dtype=dtype)
                counts["read"] += m
                yield pcd_chunk(rec, has_rgb)
            return
        points = n if "POINTS" in head else None
        yield from _pcd_ascii(fh, path, where, dtype, points, has_rgb, counts)


def _pcd_ascii(
    fh: Any,
    path: Path,
    where: str,
    dtype: np.dtype[Any],
    n: int | None,
    has_rgb: bool,
    counts: dict[str, int],
) -> Iterator[Chunk]:
    """The rows of a ``DATA ascii`` PCD, as many as its ``POINTS`` (when it has one) says."""
    fields = [
        (name, dtype[name].shape[0] if dtype[name].shape else 1) for name in dtype.names or ()
    ]
    width = sum(c for _, c in fields)
    total = 0
    while True:
        raw = [fh.readline() for _ in range(min(CLOUD_CHUNK, 65536))]
        lines = [ln.decode("ascii", "replace") for ln in raw if ln.strip()]
        if not lines:
            if n is not None and total != n:  # cut short: fewer obstacles than the camera saw
                raise InputError(
                    f"{where}: {path}: the PCD holds {total:,} point{'s' if total != 1 else ''}, "
                    f"its header says POINTS {n}",
                    path=path,
                )
            return
        try:
            vals = np.loadtxt(lines, dtype=np.float64, ndmin=2)
        except ValueError as exc:
            raise InputError(f"{where}: {path}: bad PCD ascii data: {clip(str(exc))}") from None
        if vals.shape[1] != width:
            raise InputError(
                f"{where}: {path}: bad PCD ascii data: rows of {vals.shape[1]} values; "
                f"FIELDS and COUNT give {width}",
                path=path,
            )
        total += len(vals)
        if n is not None and total > n:
            raise InputError(f"{where}: {path}: the PCD holds more than its POINTS {n}", path=path)
        rec = np.zeros(len(vals), dtype=dtype)
        col = 0
        for name, c in fields:
            rec[name] = vals[:, col : col + c].astype(dtype[name].base).reshape(rec[name].shape)
            col += c
        counts["read"] += len(rec)
        yield pcd_chunk(rec, has_rgb)


def _pcd_dtype(
    head: dict[str, list[str]], fields: list[str], path: Path, where: str
) -> tuple[np.dtype[Any], int]:
    """The record dtype and the point count a PCD header gives."""
    rows = {
        "SIZE": head.get("SIZE", ["4"] * len(fields)),
        "TYPE": head.get("TYPE", ["F"] * len(fields)),
        "COUNT": head.get("COUNT", ["1"] * len(fields)),
    }
    for key, vals in rows.items():
        if len(vals) != len(fields):
            raise InputError(
                f"{where}: {path}: bad PCD header: {key} has {len(vals)} entries, FIELDS "
                f"{len(fields)} ({' '.join(fields)})",
                path=path,
            )
    try:
        sizes = [int(v) for v in rows["SIZE"]]
        counts = [int(v) for v in rows["COUNT"]]
        n = int(head.get("POINTS", head.get("WIDTH", ["0"]))[0])
    except ValueError as exc:
        raise InputError(f"{where}: {path}: bad PCD header: {clip(str(exc))}") from None
    if n < 0:
        raise InputError(f"{where}: {path}: bad PCD header: POINTS {n}", path=path)
    cols = []
    for i, (f, size, t, c) in enumerate(zip(fields, sizes, rows["TYPE"], counts, strict=True)):
        if (t.upper(), size) not in _PCD_TYPES or c < 1:
            raise InputError(
                f"{where}: {path}: bad PCD header: field {f!r} has TYPE {t}, SIZE {size}, "
                f"COUNT {c}; types F 4/8, I and U 1/2/4/8, COUNT >= 1",
                path=path,
            )
        cols.append((f"{f}_{i}" if f == "_" else f, _PCD_TYPES[(t.upper(), size)], (c,)))
    try:
        return np.dtype(cols), n
    except (ValueError, TypeError) as exc:
        raise InputError(f"{where}: {path}: bad PCD header: {clip(str(exc))}") from None


def pcd_chunk(rec: np.ndarray, has_rgb: bool) -> Chunk:
    pts = np.stack([rec[k].reshape(len(rec), -1)[:, 0].astype(np.float64) for k in "xyz"], axis=1)
    cols = None
    if has_rgb:
        key = "rgb" if "rgb" in (rec.dtype.names or ()) else "rgba"
        packed = np.ascontiguousarray(rec[key].reshape(len(rec), -1)[:, 0])
        u = packed.view(np.uint32) if packed.dtype.itemsize == 4 else packed.astype(np.uint32)
        cols = np.stack([(u >> 16) & 255, (u >> 8) & 255, u & 255], axis=1).astype(np.uint8)
    return Chunk(pts, None, cols)
