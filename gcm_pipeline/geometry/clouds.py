"""Point clouds on a voxel grid: the processed scene cloud and how it is built.

A :class:`PointCloud` holds the occupied voxels of a scene cloud in the world
frame: one row per (voxel, segment) pair, the point being the voxel's centre.
The grid is the world's: voxel ``k`` along an axis spans
``[k * voxel_size, (k + 1) * voxel_size)``, the cells of an octree built with
the same resolution (coal's ``makeOctree``), so the voxels and the octree's
occupied cells are the same boxes.

:class:`VoxelGrid` builds one chunk by chunk, with memory bounded by the
occupied voxels, not by the points read (a cloud of 10^8 points is read in
chunks and never held at once). The readers of the file formats are in
:mod:`gcm_pipeline.sources.clouds`; the collision shapes in
:mod:`gcm_pipeline.robot.collision.world`.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from gcm_pipeline.bounds import MAX_CLOUD_VOXELS, MAX_LENGTH
from gcm_pipeline.errors import InputError

__all__ = [
    "MIN_VOXEL_SIZE",
    "NO_SEGMENT",
    "PointCloud",
    "VoxelGrid",
    "grid_reach",
    "key_centres",
    "voxel_keys",
]

#: Smallest voxel edge [m]: the packed voxel keys (21 bits per axis) cover
#: +-MAX_LENGTH from the origin at this size.
MIN_VOXEL_SIZE = 0.001
#: The segment id of points without a segmentation.
NO_SEGMENT = -1
_BITS = 21
_OFFSET = 1 << (_BITS - 1)
_MASK = (1 << _BITS) - 1


@dataclass(frozen=True)
class PointCloud:
    """A scene point cloud on a voxel grid, in the world frame.

    Attributes:
        points: Voxel centres (N, 3) float64 [m], world frame; a voxel holding
            points of several segments appears once per segment.
        voxel_size: Edge of the voxels [m].
        colors: Colour (N, 3) uint8 (RGB) of a point of each voxel, or None.
        segments: Segment id (N,) int64 of each row (:data:`NO_SEGMENT` without
            a segmentation).
        counts: What reading did: ``read`` (points or depth pixels read),
            ``non_finite`` (NaN or infinite points dropped), ``no_depth`` (depth
            pixels <= 0, not points), ``beyond_max_depth``, ``outside_crop``,
            ``excluded_segments``, ``excluded_object`` (points dropped), ``kept``
            (points voxelised) and ``voxels`` (rows of ``points``).
        name: The cloud's name (``cloud_<i>`` or the config's ``name``).
        source: The file read.
    """

    points: np.ndarray
    voxel_size: float
    colors: np.ndarray | None = None
    segments: np.ndarray | None = None
    counts: dict[str, int] = field(default_factory=dict)
    name: str = "cloud"
    source: str = ""

    def __len__(self) -> int:
        return len(self.points)

    def occupied(self, exclude_segments: tuple[int, ...] = ()) -> np.ndarray:
        """Centres (M, 3) of the voxels occupied by a segment not in ``exclude_segments``.

        Each voxel once (a voxel shared by an excluded segment and another one stays).
        """
        pts = self.points
        if exclude_segments and self.segments is not None:
            pts = pts[~np.isin(self.segments, np.asarray(exclude_segments, dtype=np.int64))]
        # np.unique's answer by a sort: np.unique took seconds on a million voxels, in one
        # call a signal cannot interrupt
        keys = np.sort(voxel_keys(pts, self.voxel_size))
        keys = keys[np.concatenate(([True], keys[1:] != keys[:-1]))] if len(keys) else keys
        return key_centres(keys, self.voxel_size)

    def __repr__(self) -> str:
        return (
            f"PointCloud(name={self.name!r}, voxels={len(self)}, voxel_size={self.voxel_size}, "
            f"colors={self.colors is not None}, segments={self.segments is not None})"
        )


def voxel_keys(points: np.ndarray, voxel_size: float) -> np.ndarray:
    """Packed int64 keys (N,) of the voxels holding points (N, 3) [m] (world grid).

    The key of coal's octrees (octomap, as ``coal.makeOctree`` inserts points): the
    coordinate times ``1 / voxel_size``, rounded down; so the voxels are the
    octree's cells (also for points on a cell's boundary).

    Raises:
        InputError: A point beyond the grid's reach (:func:`grid_reach`).
    """
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    reach = grid_reach(voxel_size)
    far = np.abs(pts) >= reach
    if far.any():
        p = pts[int(np.flatnonzero(far.any(axis=1))[0])]
        raise InputError(
            f"cloud point {p.tolist()} lies {reach:g} m or more from the world origin along an "
            f"axis: beyond an octree of {voxel_size} m voxels (bounds.MAX_LENGTH caps it at "
            f"{MAX_LENGTH:g} m); wrong units or camera_pose?",
            value=p.tolist(),
        )
    k = np.floor(pts * (1.0 / voxel_size)).astype(np.int64) + _OFFSET
    return (k[:, 0] << (2 * _BITS)) | (k[:, 1] << _BITS) | k[:, 2]


def grid_reach(voxel_size: float) -> float:
    """How far from the origin the voxel grid reaches along an axis [m].

    An octree of 16 levels (coal's) spans ``2**15`` voxels each way; at most
    ``MAX_LENGTH``.
    """
    return min(MAX_LENGTH, (1 << 15) * voxel_size * 0.999)


def key_centres(keys: np.ndarray, voxel_size: float) -> np.ndarray:
    """Centres (N, 3) [m] of the voxels of packed keys (N,)."""
    k = np.stack([(keys >> (2 * _BITS)) & _MASK, (keys >> _BITS) & _MASK, keys & _MASK], axis=1)
    return (k - _OFFSET + 0.5) * voxel_size


class VoxelGrid:
    """Occupied voxels, accumulated chunk by chunk (memory: the voxels, not the points).

    Args:
        voxel_size: Edge of the voxels [m] (at least :data:`MIN_VOXEL_SIZE`).
        max_voxels: Most distinct (voxel, segment) rows kept (an error above).
        where: Config location named in errors.
    """

    def __init__(
        self, voxel_size: float, max_voxels: int = MAX_CLOUD_VOXELS, where: str = "cloud"
    ) -> None:
        if not voxel_size >= MIN_VOXEL_SIZE:
            raise InputError(f"{where}: voxel_size must be >= {MIN_VOXEL_SIZE} m, got {voxel_size}")
        self.voxel_size = float(voxel_size)
        self.max_voxels = int(max_voxels)
        self.where = where
        self._keys = np.zeros(0, np.int64)
        self._segments = np.zeros(0, np.int64)
        self._colors: np.ndarray | None = None
        self._pending: list[tuple[np.ndarray, np.ndarray, np.ndarray | None]] = []
        self._pending_rows = 0

    def add(
        self,
        points: np.ndarray,
        segments: np.ndarray | None = None,
        colors: np.ndarray | None = None,
    ) -> None:
        """Add world points (M, 3) [m] (finite), their segments (M,) and colours (M, 3) uint8."""
        if not len(points):
            return
        try:
            keys = voxel_keys(points, self.voxel_size)
        except InputError as exc:
            raise InputError(f"{self.where}: {exc}", value=exc.value) from None
        seg = (
            np.full(len(keys), NO_SEGMENT, np.int64)
            if segments is None
            else np.asarray(segments, np.int64)
        )
        col = None if colors is None else np.asarray(colors, np.uint8)
        self._pending.append(_distinct(keys, seg, col))
        self._pending_rows += len(self._pending[-1][0])
        if self._pending_rows > max(len(self._keys), 1 << 20):
            self._merge()

    def _merge(self) -> None:
        if not self._pending:
            return
        parts = [(self._keys, self._segments, self._colors), *self._pending]
        with_col = any(p[2] is not None for p in parts if len(p[0]))
        cols = None
        if with_col:
            cols = np.concatenate(
                [p[2] if p[2] is not None else np.zeros((len(p[0]), 3), np.uint8) for p in parts]
            )
        self._keys, self._segments, self._colors = _distinct(
            np.concatenate([p[0] for p in parts]), np.concatenate([p[1] for p in parts]), cols
        )
        self._pending, self._pending_rows = [], 0
        if len(self._keys) > self.max_voxels:
            raise InputError(
                f"{self.where}: more than {self.max_voxels:,} occupied voxels of "
                f"{self.voxel_size} m (bounds.MAX_CLOUD_VOXELS); raise voxel_size or crop the cloud"
            )

    def cloud(self, *, counts: dict[str, int], name: str, source: str) -> PointCloud:
        """The :class:`PointCloud` of the voxels added so far."""
        self._merge()
        counts = {**counts, "voxels": len(self._keys)}
        has_seg = bool(np.any(self._segments != NO_SEGMENT))
        return PointCloud(
            key_centres(self._keys, self.voxel_size),
            self.voxel_size,
            colors=self._colors,
            segments=self._segments if has_seg else None,
            counts=counts,
            name=name,
            source=source,
        )


def _distinct(
    keys: np.ndarray, segments: np.ndarray, colors: np.ndarray | None
) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """One row per distinct (key, segment), sorted; the colour of its first row."""
    order = np.lexsort((segments, keys))
    k, s = keys[order], segments[order]
    first = np.ones(len(k), dtype=bool)
    first[1:] = (k[1:] != k[:-1]) | (s[1:] != s[:-1])
    rows = order[first]
    return keys[rows], segments[rows], None if colors is None else colors[rows]
