"""Scene point clouds read from files, voxelised while reading.

Formats (by suffix):

``.npy``
    (N, 3) points, or an (H, W) depth image [m, times ``depth_scale``], or a
    pickled dict in Contact-GraspNet's scene layout (below).
``.npz``
    Contact-GraspNet's scene layout (``load_available_input_data``): ``depth``
    (H, W), ``K`` (3, 3) intrinsics, optional ``segmap`` (or ``seg``) (H, W)
    segment ids and ``rgb`` (H, W, 3) stored BGR as OpenCV reads it; or
    ``xyz`` (N, 3) with optional ``xyz_color`` (N, 3).
``.ply``
    Vertices (and their colours) read by trimesh.
``.pcd``
    PCL's format, ``DATA ascii`` or ``binary``, fields ``x y z`` (and ``rgb``);
    ``binary_compressed`` is refused (convert it with ``pcl_convert_pcd_ascii_binary``).

A depth image becomes points as Contact-GraspNet's ``depth2pc`` does (pixels
with depth > 0; ``x = (u - cx) z / fx``, ``y = (v - cy) z / fy``): the
camera's optical frame (OpenCV: x right, y down, z forward). Points are read
in chunks of :data:`~gcm_pipeline.bounds.CLOUD_CHUNK`, NaN and infinite ones
dropped and counted, then cut by ``max_depth`` (camera frame), moved into the
world by ``camera_pose``, cut by the ``crop`` box, the excluded segments and
the object's own points dropped, and the rest voxelised
(:class:`~gcm_pipeline.geometry.clouds.VoxelGrid`).
"""

from __future__ import annotations

import zipfile
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import trimesh

from gcm_pipeline.bounds import CLOUD_CHUNK, MAX_CLOUD_FILE_BYTES
from gcm_pipeline.errors import InputError, clip
from gcm_pipeline.geometry.clouds import PointCloud, VoxelGrid
from gcm_pipeline.rundir.arrays import npy_header, open_regular
from gcm_pipeline.sources.files.pickled import read_pickled_npy

__all__ = ["CLOUD_FORMATS", "CloudOptions", "read_cloud"]

#: Suffixes of the cloud files read.
CLOUD_FORMATS = (".npy", ".npz", ".ply", ".pcd")


@dataclass(frozen=True)
class CloudOptions:
    """How to read and process one cloud file (plain values; the config maps onto it).

    Attributes:
        path: The file.
        voxel_size: Edge of the voxels [m].
        camera_pose: Pose (4, 4) of the camera's optical frame in the world, or
            None: the points are in the world frame.
        intrinsics: (3, 3) camera matrix of a depth image (overrides a file's ``K``).
        depth_scale: Depth units to metres (0.001 for millimetres).
        segmap: File (.npy, (H, W) ints) of a depth image's segment ids.
        max_depth: Points farther along the camera's z are dropped [m].
        crop: ``(lower, upper)`` corners of a world box; points outside are dropped.
        exclude_segments: Segment ids dropped.
        exclude: ``world points (M, 3) -> (M,) bool``: points to drop (the object's).
        name: Name used in errors and the result.
        where: Config location named in errors.
    """

    path: Path
    voxel_size: float = 0.01
    camera_pose: np.ndarray | None = None
    intrinsics: np.ndarray | None = None
    depth_scale: float = 1.0
    segmap: Path | None = None
    max_depth: float | None = None
    crop: tuple[np.ndarray, np.ndarray] | None = None
    exclude_segments: tuple[int, ...] = ()
    exclude: Callable[[np.ndarray], np.ndarray] | None = None
    name: str = "cloud"
    where: str = "cloud"


class _Chunk:
    """Points (M, 3) in the file's frame with optional segments (M,) and colours (M, 3)."""

    __slots__ = ("colors", "points", "segments")

    def __init__(
        self, points: np.ndarray, segments: np.ndarray | None, colors: np.ndarray | None
    ) -> None:
        self.points, self.segments, self.colors = points, segments, colors

    def take(self, keep: np.ndarray) -> _Chunk:
        return _Chunk(
            self.points[keep],
            None if self.segments is None else self.segments[keep],
            None if self.colors is None else self.colors[keep],
        )


def read_cloud(opt: CloudOptions) -> PointCloud:
    """Read, transform, filter and voxelise one cloud file (see the module doc).

    Raises:
        InputError: Unreadable or malformed file, missing intrinsics, sizes
            that disagree, a cloud with no point left.
    """
    path = Path(opt.path)
    counts = dict.fromkeys(
        (
            "read",
            "non_finite",
            "no_depth",
            "beyond_max_depth",
            "outside_crop",
            "excluded_segments",
            "excluded_object",
            "kept",
        ),
        0,
    )
    grid = VoxelGrid(opt.voxel_size, where=f"{opt.where}: {path}")
    try:
        for chunk in _chunks(path, opt, counts):
            _add(grid, chunk, opt, counts)
    except OSError as exc:
        raise InputError(f"{opt.where}: {path}: {exc.strerror or exc}", path=path) from None
    except InputError as exc:
        if str(exc).startswith(opt.where):
            raise
        # every message names the config key first (the readers name the file)
        raise InputError(
            f"{opt.where}: {exc}",
            key=opt.where,
            value=exc.value,
            choices=exc.choices,
            path=exc.path or path,
            row=exc.row,
        ) from None
    if counts["kept"] == 0:
        told = ", ".join(f"{k} {v:,}" for k, v in counts.items() if v)
        raise InputError(
            f"{opt.where}: {path}: no point is left ({told or 'the file holds none'})", path=path
        )
    return grid.cloud(counts=counts, name=opt.name, source=str(path))


def _add(grid: VoxelGrid, chunk: _Chunk, opt: CloudOptions, counts: dict[str, int]) -> None:
    """Filter one chunk (file frame) and add what is left to the grid."""
    finite = np.all(np.isfinite(chunk.points), axis=1)
    counts["non_finite"] += int(np.count_nonzero(~finite))
    chunk = chunk.take(finite)
    if opt.max_depth is not None:
        near = chunk.points[:, 2] <= opt.max_depth
        counts["beyond_max_depth"] += int(np.count_nonzero(~near))
        chunk = chunk.take(near)
    if opt.camera_pose is not None:
        pose = opt.camera_pose
        chunk.points = chunk.points @ pose[:3, :3].T + pose[:3, 3]
    if opt.crop is not None:
        lo, hi = opt.crop
        inside = np.all((chunk.points >= lo) & (chunk.points <= hi), axis=1)
        counts["outside_crop"] += int(np.count_nonzero(~inside))
        chunk = chunk.take(inside)
    if opt.exclude_segments and chunk.segments is not None:
        other = ~np.isin(chunk.segments, np.asarray(opt.exclude_segments, dtype=np.int64))
        counts["excluded_segments"] += int(np.count_nonzero(~other))
        chunk = chunk.take(other)
    if opt.exclude is not None and len(chunk.points):
        drop = np.asarray(opt.exclude(chunk.points), dtype=bool)
        counts["excluded_object"] += int(np.count_nonzero(drop))
        chunk = chunk.take(~drop)
    counts["kept"] += len(chunk.points)
    grid.add(chunk.points, chunk.segments, chunk.colors)


# ------------------------------------------------------------------ formats


def _chunks(path: Path, opt: CloudOptions, counts: dict[str, int]) -> Iterator[_Chunk]:
    suffix = path.suffix.lower()
    if suffix not in CLOUD_FORMATS:
        raise InputError(
            f"{opt.where}: {path}: unknown cloud format {suffix!r}; choices: "
            + ", ".join(CLOUD_FORMATS),
            path=path,
            value=suffix,
            choices=CLOUD_FORMATS,
        )
    if suffix == ".ply":
        yield from _ply(path, opt, counts)
    elif suffix == ".pcd":
        yield from _pcd(path, opt, counts)
    elif suffix == ".npz":
        yield from _npz(path, opt, counts)
    else:
        yield from _npy(path, opt, counts)


class _Rows:
    """Rows of one .npy array (a file or an .npz member), read in order, block by block."""

    def __init__(self, path: Path, fh: Any, available: int, what: str) -> None:
        self.path, self.fh, self.what = path, fh, what
        version = np.lib.format.read_magic(fh)
        if version == (1, 0):
            shape, fortran, dtype = np.lib.format.read_array_header_1_0(fh)
        else:
            shape, fortran, dtype = np.lib.format.read_array_header_2_0(fh)
        if dtype.hasobject:
            raise InputError(f"{path}: {what} holds Python objects; plain arrays only", path=path)
        if fortran and len(shape) > 1:
            raise InputError(f"{path}: {what} is stored in Fortran order; save it in C order")
        if not np.issubdtype(dtype, np.number):
            raise InputError(f"{path}: {what} has dtype {dtype}; numbers are needed", path=path)
        self.shape, self.dtype = tuple(int(k) for k in shape), dtype
        self.row_items = int(np.prod(self.shape[1:], dtype=np.int64)) if len(shape) > 1 else 1
        need = int(np.prod(self.shape, dtype=np.int64)) * dtype.itemsize + fh.tell()
        if need > available:
            raise InputError(
                f"{path}: {what} is truncated: its header says shape {self.shape} "
                f"({need:,} bytes) but there are {available:,}",
                path=path,
            )

    def read(self, rows: int) -> np.ndarray:
        n = rows * self.row_items
        data = self.fh.read(n * self.dtype.itemsize)
        if len(data) != n * self.dtype.itemsize:
            raise InputError(f"{self.path}: {self.what} is truncated", path=self.path)
        return np.frombuffer(data, dtype=self.dtype).reshape(rows, *self.shape[1:])


def _npy(path: Path, opt: CloudOptions, counts: dict[str, int]) -> Iterator[_Chunk]:
    with open_regular(path) as fh:
        size = path.stat().st_size
        shape, dtype = _peek_header(path, fh)
        if dtype.hasobject:  # Contact-GraspNet's pickled dict
            if size > MAX_CLOUD_FILE_BYTES:
                raise InputError(
                    f"{opt.where}: {path}: a pickled .npy of {size:,} bytes is above "
                    f"{MAX_CLOUD_FILE_BYTES:,} (bounds.MAX_CLOUD_FILE_BYTES); save the "
                    "points as a plain (N, 3) .npy",
                    path=path,
                )
            value = read_pickled_npy(path, max_values=size)
            if not isinstance(value, dict):
                raise InputError(f"{path}: a pickled .npy must hold a dict of arrays", path=path)
            yield from _scene_dict(
                path, {k: _MemRows(np.asarray(v)) for k, v in value.items()}, opt, counts
            )
            return
        fh.seek(0)
        rows = _Rows(path, fh, size, "the array")
        yield from _array_chunks(path, rows, opt, counts, None, None)


def _peek_header(path: Path, fh: Any) -> tuple[tuple[int, ...], np.dtype[Any]]:
    try:
        version = np.lib.format.read_magic(fh)
        if version == (1, 0):
            shape, _, dtype = np.lib.format.read_array_header_1_0(fh, max_header_size=10_000)
        else:
            shape, _, dtype = np.lib.format.read_array_header_2_0(fh, max_header_size=10_000)
    except (ValueError, OSError, EOFError) as exc:
        raise InputError(f"{path}: not a readable .npy: {clip(str(exc))}", path=path) from None
    return shape, dtype


class _MemRows:
    """An in-memory array with the :class:`_Rows` interface."""

    def __init__(self, arr: np.ndarray) -> None:
        self.arr, self.shape, self.dtype, self.at = arr, arr.shape, arr.dtype, 0

    def read(self, rows: int) -> np.ndarray:
        out = self.arr[self.at : self.at + rows]
        self.at += rows
        return out


def _npz(path: Path, opt: CloudOptions, counts: dict[str, int]) -> Iterator[_Chunk]:
    try:
        with open_regular(path) as raw, zipfile.ZipFile(raw) as zf:
            infos = {i.filename[:-4]: i for i in zf.infolist() if i.filename.endswith(".npy")}
            opened = {}
            try:
                for name, info in infos.items():
                    if name in ("depth", "K", "segmap", "seg", "rgb", "xyz", "xyz_color"):
                        fh = zf.open(info)
                        opened[name] = _Rows(path, fh, info.file_size, f"array {name!r}")
                yield from _scene_dict(path, opened, opt, counts)
            finally:
                for rows in opened.values():
                    rows.fh.close()
    except InputError:
        raise
    except (zipfile.BadZipFile, OSError, EOFError, ValueError) as exc:
        raise InputError(f"{path}: not a readable .npz: {clip(str(exc))}", path=path) from None


def _scene_dict(
    path: Path, arrays: dict[str, Any], opt: CloudOptions, counts: dict[str, int]
) -> Iterator[_Chunk]:
    """Contact-GraspNet's scene keys: ``depth`` + ``K`` (+ ``segmap``, ``rgb``) or ``xyz``."""
    if "depth" in arrays:
        seg = arrays.get("segmap", arrays.get("seg"))
        k = opt.intrinsics
        if k is None and "K" in arrays:
            kk = arrays["K"]
            k = np.asarray(kk.read(kk.shape[0] if kk.shape else 1), dtype=np.float64)
        yield from _depth_chunks(path, arrays["depth"], k, seg, arrays.get("rgb"), opt, counts)
    elif "xyz" in arrays:
        yield from _array_chunks(path, arrays["xyz"], opt, counts, None, arrays.get("xyz_color"))
    else:
        raise InputError(
            f"{opt.where}: {path}: no cloud in it: Contact-GraspNet's scene keys are "
            f"'depth' + 'K' (+ 'segmap', 'rgb') or 'xyz' (+ 'xyz_color'); it has "
            f"{sorted(arrays)}",
            path=path,
        )


def _array_chunks(
    path: Path,
    rows: Any,
    opt: CloudOptions,
    counts: dict[str, int],
    segments: Any,
    colors: Any,
) -> Iterator[_Chunk]:
    """An (N, 3) array of points, or (H, W) depth."""
    shape = rows.shape
    if len(shape) == 2 and shape[1] != 3:
        yield from _depth_chunks(path, rows, opt.intrinsics, None, None, opt, counts)
        return
    if len(shape) != 2:
        raise InputError(
            f"{opt.where}: {path}: points must be (N, 3) or a depth image (H, W); got shape "
            f"{tuple(shape)}",
            path=path,
        )
    if colors is not None and tuple(colors.shape) != (shape[0], 3):
        raise InputError(
            f"{opt.where}: {path}: xyz_color must be (N, 3) like xyz, got {tuple(colors.shape)}",
            path=path,
        )
    for a in range(0, shape[0], CLOUD_CHUNK):
        m = min(CLOUD_CHUNK, shape[0] - a)
        pts = np.asarray(rows.read(m), dtype=np.float64)
        counts["read"] += m
        yield _Chunk(pts, None, None if colors is None else _as_colors(colors.read(m)))


def _as_colors(c: np.ndarray) -> np.ndarray:
    c = np.asarray(c)
    if np.issubdtype(c.dtype, np.floating) and c.size and np.nanmax(c) <= 1.0:
        c = c * 255.0
    return np.clip(np.nan_to_num(c), 0, 255).astype(np.uint8)


def _check_intrinsics(path: Path, k: np.ndarray | None, opt: CloudOptions) -> np.ndarray:
    if k is None:
        raise InputError(
            f"{opt.where}: {path}: a depth image needs intrinsics: give {opt.where}.intrinsics "
            "[[fx, 0, cx], [0, fy, cy], [0, 0, 1]] or a 'K' array in the .npz",
            path=path,
        )
    k = np.asarray(k, dtype=np.float64)
    if k.size != 9:
        raise InputError(
            f"{opt.where}: {path}: intrinsics K must be 3 x 3 (9 numbers), got shape {k.shape}",
            path=path,
            value=list(k.shape),
        )
    k = k.reshape(3, 3)
    if not np.all(np.isfinite(k)) or k[0, 0] <= 0 or k[1, 1] <= 0:
        raise InputError(
            f"{opt.where}: {path}: intrinsics K needs finite values and fx, fy > 0, got "
            f"{k.tolist()}",
            path=path,
        )
    return k


def _depth_chunks(
    path: Path,
    depth: Any,
    k: np.ndarray | None,
    seg: Any,
    rgb: Any,
    opt: CloudOptions,
    counts: dict[str, int],
) -> Iterator[_Chunk]:
    """Depth rows, block by block, as camera-frame points (``depth2pc``)."""
    kk = _check_intrinsics(path, k, opt)
    if len(depth.shape) != 2:
        raise InputError(
            f"{opt.where}: {path}: depth must be (H, W), got shape {tuple(depth.shape)}", path=path
        )
    h, w = depth.shape
    if seg is None and opt.segmap is not None:
        seg = _MemRows(_read_segmap(opt))
    if seg is not None and tuple(seg.shape) != (h, w):
        raise InputError(
            f"{opt.where}: {path}: the segmentation is {tuple(seg.shape)}, the depth image "
            f"({h}, {w}); they must be the same size",
            path=path,
            value=list(seg.shape),
        )
    if rgb is not None and tuple(rgb.shape[:2]) != (h, w):
        raise InputError(
            f"{opt.where}: {path}: rgb is {tuple(rgb.shape)}, the depth image ({h}, {w}); "
            "they must be the same size",
            path=path,
        )
    u = np.arange(w, dtype=np.float64)
    block = max(1, CLOUD_CHUNK // max(w, 1))
    for a in range(0, h, block):
        m = min(block, h - a)
        z = np.asarray(depth.read(m), dtype=np.float64) * opt.depth_scale
        segs = None if seg is None else np.asarray(seg.read(m)).astype(np.int64)
        cols = None if rgb is None else np.asarray(rgb.read(m))[..., 2::-1]  # BGR -> RGB
        counts["read"] += z.size
        valid = ~(z <= 0)  # NaN stays (dropped and counted as non-finite)
        counts["no_depth"] += int(np.count_nonzero(~valid))
        vv, uu = np.nonzero(valid)
        zz = z[vv, uu]
        pts = np.empty((zz.size, 3))
        pts[:, 0] = (u[uu] - kk[0, 2]) * zz / kk[0, 0]
        pts[:, 1] = (vv + a - kk[1, 2]) * zz / kk[1, 1]
        pts[:, 2] = zz
        yield _Chunk(
            pts,
            None if segs is None else segs[vv, uu],
            None if cols is None else _as_colors(cols[vv, uu]),
        )


def _read_segmap(opt: CloudOptions) -> np.ndarray:
    assert opt.segmap is not None
    path = Path(opt.segmap)
    try:
        with open_regular(path) as fh:
            shape, dtype = npy_header(path, fh, "the segmentation", path.stat().st_size)
            fh.seek(0)
            arr = np.lib.format.read_array(fh, allow_pickle=False)
    except OSError as exc:
        raise InputError(f"{opt.where}.segmap: {path}: {exc}", path=path) from None
    if not np.issubdtype(dtype, np.integer) and not np.issubdtype(dtype, np.floating):
        raise InputError(f"{opt.where}.segmap: {path}: dtype {dtype} is not a number", path=path)
    return np.asarray(arr)


def _ply(path: Path, opt: CloudOptions, counts: dict[str, int]) -> Iterator[_Chunk]:
    _check_whole(path, opt)
    try:
        loaded = trimesh.load(str(path), process=False)
    except Exception as exc:  # trimesh raises many kinds on a bad file
        raise InputError(f"{opt.where}: {path}: not a readable .ply: {clip(str(exc))}") from None
    pts = np.asarray(getattr(loaded, "vertices", np.zeros((0, 3))), dtype=np.float64)
    cols = getattr(loaded, "colors", None)
    if cols is None or len(cols) != len(pts):
        visual = getattr(loaded, "visual", None)
        cols = getattr(visual, "vertex_colors", None)
    cols = None if cols is None or len(cols) != len(pts) else np.asarray(cols)[:, :3]
    counts["read"] += len(pts)
    for a in range(0, len(pts), CLOUD_CHUNK):
        sl = slice(a, a + CLOUD_CHUNK)
        yield _Chunk(pts[sl], None, None if cols is None else _as_colors(cols[sl]))


def _check_whole(path: Path, opt: CloudOptions) -> None:
    size = path.stat().st_size
    if size > MAX_CLOUD_FILE_BYTES:
        raise InputError(
            f"{opt.where}: {path}: {size:,} bytes is above {MAX_CLOUD_FILE_BYTES:,} "
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


def _pcd(path: Path, opt: CloudOptions, counts: dict[str, int]) -> Iterator[_Chunk]:
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
                f"{opt.where}: {path}: PCD 'DATA binary_compressed' is not read; convert it "
                "to binary or ascii (pcl_convert_pcd_ascii_binary in.pcd out.pcd 1)",
                path=path,
            )
        if data not in ("ascii", "binary") or "FIELDS" not in head:
            raise InputError(f"{opt.where}: {path}: not a PCD file (no FIELDS/DATA header)")
        fields = head["FIELDS"]
        try:
            sizes = [int(s) for s in head.get("SIZE", ["4"] * len(fields))]
            types = head.get("TYPE", ["F"] * len(fields))
            counts_ = [int(c) for c in head.get("COUNT", ["1"] * len(fields))]
            n = int(head.get("POINTS", head.get("WIDTH", ["0"]))[0])
            dtype = np.dtype(
                [
                    (f"{f}_{i}" if f == "_" else f, _PCD_TYPES[(t.upper(), s)], (c,))
                    for i, (f, s, t, c) in enumerate(
                        zip(fields, sizes, types, counts_, strict=True)
                    )
                ]
            )
        except (KeyError, ValueError, TypeError) as exc:
            raise InputError(f"{opt.where}: {path}: bad PCD header: {clip(str(exc))}") from None
        if not {"x", "y", "z"} <= set(fields):
            raise InputError(f"{opt.where}: {path}: PCD fields {fields} lack x, y, z", path=path)
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
                yield _pcd_chunk(rec, has_rgb)
            return
        while True:
            raw = [fh.readline() for _ in range(min(CLOUD_CHUNK, 65536))]
            lines = [ln.decode("ascii", "replace") for ln in raw if ln.strip()]
            if not lines:
                return
            try:
                vals = np.loadtxt(lines, dtype=np.float64, ndmin=2)
            except ValueError as exc:
                raise InputError(f"{path}: bad PCD ascii data: {clip(str(exc))}") from None
            rec = np.zeros(len(vals), dtype=dtype)
            col = 0
            for name in dtype.names or ():
                c = dtype[name].shape[0] if dtype[name].shape else 1
                rec[name] = vals[:, col : col + c].astype(dtype[name].base).reshape(rec[name].shape)
                col += c
            counts["read"] += len(rec)
            yield _pcd_chunk(rec, has_rgb)


def _pcd_chunk(rec: np.ndarray, has_rgb: bool) -> _Chunk:
    pts = np.stack([rec[k].reshape(len(rec), -1)[:, 0].astype(np.float64) for k in "xyz"], axis=1)
    cols = None
    if has_rgb:
        key = "rgb" if "rgb" in (rec.dtype.names or ()) else "rgba"
        packed = np.ascontiguousarray(rec[key].reshape(len(rec), -1)[:, 0])
        u = packed.view(np.uint32) if packed.dtype.itemsize == 4 else packed.astype(np.uint32)
        cols = np.stack([(u >> 16) & 255, (u >> 8) & 255, u & 255], axis=1).astype(np.uint8)
    return _Chunk(pts, None, cols)
