"""Scene point clouds read from files, voxelised while reading.

Formats (by suffix):

``.npy``
    (N, 3) points, or an (H, W) depth image [m, times ``depth_scale``], or a
    pickled dict in Contact-GraspNet's scene layout (below).
``.npz``
    Contact-GraspNet's scene layout (``load_available_input_data``): ``depth``
    (H, W), ``K`` (3, 3) intrinsics, optional ``segmap`` (or ``seg``) (H, W)
    segment ids and ``rgb`` (H, W, 3) stored BGR as OpenCV reads it; or
    ``xyz`` (N, 3) with optional ``xyz_color`` (N, 3); or ``pc_full`` (N, 3)
    with optional ``pc_colors`` (N, 3, BGR) as Contact-GraspNet's inference keeps them.
``.ply``
    Vertices (and their colours) read by trimesh.
``.png``
    A single-channel depth image (16-bit millimetres: ``depth_scale: 0.001``),
    as GraspNet-1Billion and Contact-GraspNet store them; ``intrinsics`` and
    an optional ``segmap`` (``.npy`` or a label ``.png``) from the config.
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

from gcm_pipeline.bounds import CLOUD_CHUNK, MAX_CLOUD_FILE_BYTES
from gcm_pipeline.errors import InputError, clip
from gcm_pipeline.geometry.clouds import PointCloud, VoxelGrid
from gcm_pipeline.rundir.arrays import ZIP_ERRORS, npy_header, open_regular
from gcm_pipeline.sources.files.cloud_formats import (
    Chunk,
    MemRows,
    Rows,
    as_colors,
    pcd_chunks,
    ply_chunks,
    read_png,
)
from gcm_pipeline.sources.files.pickled import read_pickled_npy

__all__ = ["CLOUD_FORMATS", "CloudOptions", "read_cloud"]

#: Suffixes of the cloud files read.
CLOUD_FORMATS = (".npy", ".npz", ".ply", ".pcd", ".png")


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


def _add(grid: VoxelGrid, chunk: Chunk, opt: CloudOptions, counts: dict[str, int]) -> None:
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
    if opt.exclude_segments and chunk.segments is None:
        raise InputError(
            f"{opt.where}: {opt.path}: exclude_segments {list(opt.exclude_segments)} needs "
            "segment ids, and this cloud has none: give a depth image's segmap (or the "
            ".npz's 'segmap'), or drop exclude_segments",
            key=f"{opt.where}.exclude_segments",
            path=opt.path,
        )
    if opt.exclude_segments:
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


def _chunks(path: Path, opt: CloudOptions, counts: dict[str, int]) -> Iterator[Chunk]:
    suffix = path.suffix.lower()
    if suffix not in CLOUD_FORMATS:
        raise InputError(
            f"{opt.where}: {path}: unknown cloud format {suffix!r}; choices: "
            + ", ".join(CLOUD_FORMATS),
            path=path,
            value=suffix,
            choices=CLOUD_FORMATS,
        )
    if suffix in (".ply", ".pcd"):
        points_only(path, opt, f"points ({suffix})")
    if suffix == ".ply":
        yield from ply_chunks(path, opt.where, counts)
    elif suffix == ".png":
        depth = MemRows(read_png(path, opt.where))
        yield from _depth_chunks(path, depth, opt.intrinsics, None, None, opt, counts)
    elif suffix == ".pcd":
        yield from pcd_chunks(path, opt.where, counts)
    elif suffix == ".npz":
        yield from _npz(path, opt, counts)
    else:
        yield from _npy(path, opt, counts)


def _npy(path: Path, opt: CloudOptions, counts: dict[str, int]) -> Iterator[Chunk]:
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
                # a key set to None (no segmap, no rgb) is a key left out
                path,
                {k: MemRows(np.asarray(v)) for k, v in value.items() if v is not None},
                opt,
                counts,
                sorted(f"{k}" + (" (None)" if v is None else "") for k, v in value.items()),
            )
            return
        fh.seek(0)
        rows = Rows(path, fh, size, "the array")
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


def _npz(path: Path, opt: CloudOptions, counts: dict[str, int]) -> Iterator[Chunk]:
    try:
        with open_regular(path) as raw, zipfile.ZipFile(raw) as zf:
            infos = {i.filename[:-4]: i for i in zf.infolist() if i.filename.endswith(".npy")}
            opened = {}
            try:
                for name, info in infos.items():
                    if name in _SCENE_KEYS:
                        fh = zf.open(info)
                        opened[name] = Rows(path, fh, info.file_size, f"array {name!r}")
                yield from _scene_dict(path, opened, opt, counts, sorted(infos))
            finally:
                for rows in opened.values():
                    rows.fh.close()
    except InputError:
        raise
    except ZIP_ERRORS as exc:
        why = clip(str(exc) or type(exc).__name__)
        raise InputError(f"{path}: not a readable .npz: {why}", path=path) from None


#: The keys of a Contact-GraspNet scene read from an ``.npz`` (or a pickled ``.npy`` dict).
_SCENE_KEYS = ("depth", "K", "segmap", "seg", "rgb", "xyz", "xyz_color", "pc_full", "pc_colors")


def _scene_dict(
    path: Path,
    arrays: dict[str, Any],
    opt: CloudOptions,
    counts: dict[str, int],
    members: list[str] | None = None,
) -> Iterator[Chunk]:
    """Contact-GraspNet's scene keys: ``depth`` + ``K`` (+ ``segmap``, ``rgb``) or ``xyz``.

    ``pc_full`` (+ ``pc_colors``, BGR) as its inference gives them is read like ``xyz``.
    """
    if "depth" in arrays:
        seg = arrays.get("segmap", arrays.get("seg"))
        k = opt.intrinsics
        if k is None and "K" in arrays:
            kk = arrays["K"]
            _real(path, kk, opt, "K")
            k = np.asarray(kk.read(kk.shape[0] if kk.shape else 1), dtype=np.float64)
        yield from _depth_chunks(path, arrays["depth"], k, seg, arrays.get("rgb"), opt, counts)
    elif "xyz" in arrays:
        yield from _array_chunks(path, arrays["xyz"], opt, counts, None, arrays.get("xyz_color"))
    elif "pc_full" in arrays:
        bgr = arrays.get("pc_colors")
        yield from _array_chunks(path, arrays["pc_full"], opt, counts, None, bgr, bgr=True)
    else:
        raise InputError(
            f"{opt.where}: {path}: no cloud in it: Contact-GraspNet's scene keys are "
            f"'depth' + 'K' (+ 'segmap', 'rgb'), 'xyz' (+ 'xyz_color') or 'pc_full' "
            f"(+ 'pc_colors'); it has {sorted(arrays) if members is None else members}",
            path=path,
        )


def _array_chunks(
    path: Path,
    rows: Any,
    opt: CloudOptions,
    counts: dict[str, int],
    segments: Any,
    colors: Any,
    bgr: bool = False,
) -> Iterator[Chunk]:
    """An (N, 3) array of points, or (H, W) depth."""
    shape = rows.shape
    _real(path, rows, opt, "the points")
    if len(shape) == 2 and shape[1] != 3:
        yield from _depth_chunks(path, rows, opt.intrinsics, None, None, opt, counts)
        return
    if len(shape) != 2:
        raise InputError(
            f"{opt.where}: {path}: points must be (N, 3) or a depth image (H, W); got shape "
            f"{tuple(shape)}",
            path=path,
        )
    points_only(path, opt, f"(N, 3) points, shape {tuple(shape)}")
    if colors is not None and tuple(colors.shape) != (shape[0], 3):
        raise InputError(
            f"{opt.where}: {path}: the colours must be (N, 3) like the points, got "
            f"{tuple(colors.shape)}",
            path=path,
        )
    for a in range(0, shape[0], CLOUD_CHUNK):
        m = min(CLOUD_CHUNK, shape[0] - a)
        pts = np.asarray(rows.read(m), dtype=np.float64)
        counts["read"] += m
        cols = None if colors is None else np.asarray(colors.read(m))
        if cols is not None and bgr:
            cols = cols[:, ::-1]
        yield Chunk(pts, None, None if cols is None else as_colors(cols))


def points_only(path: Path, opt: CloudOptions, what: str) -> None:
    """Refuse a depth image's keys (``intrinsics``, ``segmap``) for a file of points."""
    for key in ("intrinsics", "segmap"):
        if getattr(opt, key) is not None:
            raise InputError(
                f"{opt.where}.{key}: applies to a depth image, and {path} holds {what}; drop {key}",
                key=f"{opt.where}.{key}",
                path=path,
            )


def _real(path: Path, rows: Any, opt: CloudOptions, what: str = "the array") -> None:
    """Refuse an array that is not real numbers (complex, bool, strings, objects)."""
    if np.dtype(rows.dtype).kind not in "iuf":
        raise InputError(
            f"{opt.where}: {path}: {what} has dtype {rows.dtype}: real numbers are needed",
            path=path,
            value=str(rows.dtype),
        )


def _check_intrinsics(
    path: Path, k: np.ndarray | None, opt: CloudOptions, shape: tuple[int, ...]
) -> np.ndarray:
    if k is None:
        raise InputError(
            f"{opt.where}: {path}: a depth image {tuple(shape)} needs intrinsics: give "
            f"{opt.where}.intrinsics [[fx, 0, cx], [0, fy, cy], [0, 0, 1]] or a 'K' array in "
            "the .npz (points are (N, 3))",
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
) -> Iterator[Chunk]:
    """Depth rows, block by block, as camera-frame points (``depth2pc``)."""
    if len(depth.shape) != 2:
        raise InputError(
            f"{opt.where}: {path}: depth must be (H, W), got shape {tuple(depth.shape)}", path=path
        )
    kk = _check_intrinsics(path, k, opt, depth.shape)
    h, w = depth.shape
    if opt.segmap is not None:  # the config's segmap overrides the file's (as intrinsics K)
        seg = MemRows(_read_segmap(opt))
    if seg is not None and tuple(seg.shape) != (h, w):
        raise InputError(
            f"{opt.where}: {path}: the segmentation is {tuple(seg.shape)}, the depth image "
            f"({h}, {w}); they must be the same size",
            path=path,
            value=list(seg.shape),
        )
    _real(path, depth, opt, "the depth image")
    if np.dtype(depth.dtype).kind in "iu" and opt.depth_scale == 1.0:
        raise InputError(
            f"{opt.where}.depth_scale: {path}: an integer ({depth.dtype}) depth image is in "
            "sensor units, not metres: give depth_scale (0.001 for millimetres)",
            key=f"{opt.where}.depth_scale",
            path=path,
        )
    if rgb is not None and (tuple(rgb.shape[:2]) != (h, w) or tuple(rgb.shape[2:]) not in _RGB):
        raise InputError(
            f"{opt.where}: {path}: rgb is {tuple(rgb.shape)}; it must be ({h}, {w}, 3) like "
            f"the depth image ({h}, {w})",
            path=path,
        )
    u = np.arange(w, dtype=np.float64)
    block = max(1, CLOUD_CHUNK // max(w, 1))
    for a in range(0, h, block):
        m = min(block, h - a)
        z = np.asarray(depth.read(m), dtype=np.float64) * opt.depth_scale
        segs = None if seg is None else segment_ids(np.asarray(seg.read(m)), path, opt)
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
        yield Chunk(
            pts,
            None if segs is None else segs[vv, uu],
            None if cols is None else as_colors(cols[vv, uu]),
        )


#: The channels of an ``rgb`` image (BGR, or BGRA).
_RGB = ((3,), (4,))


def segment_ids(seg: np.ndarray, path: Path, opt: CloudOptions) -> np.ndarray:
    """Segment ids (int64) of a block of a segmentation: whole numbers only."""
    if seg.dtype.kind == "f":
        bad = ~np.isfinite(seg) | (seg != np.round(seg)) | (np.abs(seg) > 2.0**53)
    elif seg.dtype.kind == "u" and seg.dtype.itemsize == 8:
        bad = seg > np.iinfo(np.int64).max
    elif seg.dtype.kind in "iub":
        return seg.astype(np.int64)
    else:
        raise InputError(
            f"{opt.where}: {path}: the segmentation has dtype {seg.dtype}; segment ids are "
            "whole numbers",
            path=path,
        )
    if np.any(bad):
        raise InputError(
            f"{opt.where}: {path}: the segmentation holds {seg[bad].flat[0].item()}; segment ids "
            "are whole numbers",
            path=path,
            value=seg[bad].flat[0].item(),
        )
    return seg.astype(np.int64)


def _read_segmap(opt: CloudOptions) -> np.ndarray:
    assert opt.segmap is not None
    path = Path(opt.segmap)
    if path.suffix.lower() == ".png":
        return read_png(path, f"{opt.where}.segmap")
    try:
        with open_regular(path) as fh:
            shape, dtype = npy_header(path, fh, "the segmentation", path.stat().st_size)
            fh.seek(0)
            arr = np.lib.format.read_array(fh, allow_pickle=False)
    except OSError as exc:
        raise InputError(f"{opt.where}.segmap: {path}: {exc}", path=path) from None
    if dtype.kind not in "iufb":
        raise InputError(f"{opt.where}.segmap: {path}: dtype {dtype} is not a number", path=path)
    return np.asarray(arr)
