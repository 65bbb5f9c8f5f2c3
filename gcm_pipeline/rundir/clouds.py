"""``cloud.npz``: the run's processed scene clouds (``environment.point_clouds``).

Arrays (all clouds of the run concatenated; N voxels, K clouds):

- ``points`` (N, 3) float64: voxel centres in the world frame [m];
- ``colors`` (N, 3) uint8: RGB (zeros where ``has_colors`` of its cloud is false);
- ``segments`` (N,) int64: segment ids (-1: no segmentation);
- ``cloud`` (N,) int64: index of each row's cloud;
- ``names`` (K,) str, ``voxel_size`` (K,) float64, ``has_colors`` (K,) bool.

The target object's excluded points are not in it (what the collision checker
sees, the octree's occupied cells being the voxels around these centres).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from gcm_pipeline.geometry.clouds import NO_SEGMENT, PointCloud
from gcm_pipeline.rundir.arrays import read_npz

__all__ = ["CLOUD_FILE", "read_clouds", "write_clouds"]

CLOUD_FILE = "cloud.npz"
#: Most bytes ``cloud.npz`` is read back with (the voxels of 16 clouds at the size bound).
_MAX_BYTES = 16 * 40 * 20_000_000


def write_clouds(clouds: list[PointCloud], path: str | Path) -> None:
    """Write the clouds to ``path`` (see the module doc)."""
    n = [len(c) for c in clouds]
    total = sum(n)
    colors = np.zeros((total, 3), np.uint8)
    segments = np.full(total, NO_SEGMENT, np.int64)
    at = 0
    for c in clouds:
        if c.colors is not None:
            colors[at : at + len(c)] = c.colors
        if c.segments is not None:
            segments[at : at + len(c)] = c.segments
        at += len(c)
    np.savez(
        path,
        points=np.concatenate([c.points for c in clouds]) if clouds else np.zeros((0, 3)),
        colors=colors,
        segments=segments,
        cloud=np.repeat(np.arange(len(clouds), dtype=np.int64), n),
        names=np.array([c.name for c in clouds], dtype=str),
        voxel_size=np.array([c.voxel_size for c in clouds], dtype=np.float64),
        has_colors=np.array([c.colors is not None for c in clouds], dtype=bool),
    )


def read_clouds(path: str | Path) -> list[PointCloud]:
    """The clouds of a ``cloud.npz`` (counts and sources are in ``summary.json``)."""
    a = read_npz(path, max_bytes=_MAX_BYTES)
    out = []
    for k, name in enumerate(a["names"].tolist()):
        rows = a["cloud"] == k
        seg = a["segments"][rows]
        out.append(
            PointCloud(
                a["points"][rows],
                float(a["voxel_size"][k]),
                colors=a["colors"][rows] if a["has_colors"][k] else None,
                segments=seg if np.any(seg != NO_SEGMENT) else None,
                name=str(name),
            )
        )
    return out
