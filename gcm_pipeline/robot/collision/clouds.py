"""Point clouds as collision shapes: coal octrees over tiles of occupied voxels.

A cloud's occupied voxels (:class:`~gcm_pipeline.geometry.clouds.PointCloud`,
world grid) are split into at most ``max_tiles`` tiles, each a coal ``OcTree``
with the cloud's resolution and its own tight bounding box: a
:class:`~gcm_pipeline.robot.collision.world.WorldShape` of kind ``environment``
like any obstacle. The broad phase bounds an octree by that box (the union of
its occupied cells, :class:`~gcm_pipeline.robot.collision.broadphase.ShapeBound`),
which is sound (never more than the true distance) and, the tiles being
small, useful in a cluttered scene; coal decides the rest (octree against
meshes and primitives). Tiles come from a k-d split: the tile of largest
extent is cut at its median voxel along its longest axis until there are
``max_tiles`` or every tile is at most :data:`MIN_TILE_VOXELS` voxels across.
Each tile is one more world shape: it costs the checker about as much memory
as an obstacle (see :data:`~gcm_pipeline.bounds.MAX_OBSTACLES`).
"""

from __future__ import annotations

import coal
import numpy as np

from gcm_pipeline.robot.collision.pairs import coal_transform
from gcm_pipeline.robot.collision.world import WorldShape

__all__ = ["MAX_TILES", "MIN_TILE_VOXELS", "cloud_shapes", "octree", "tiles", "within_distance"]

#: Default most tiles (octrees) per cloud.
MAX_TILES = 16
#: A tile at most this many voxels across is not split further.
MIN_TILE_VOXELS = 4


def octree(points: np.ndarray, voxel_size: float) -> coal.OcTree:
    """A coal octree of ``points`` (M, 3) [m] at resolution ``voxel_size`` (world grid)."""
    return coal.makeOctree(np.ascontiguousarray(points, dtype=np.float64), float(voxel_size))


def tiles(points: np.ndarray, voxel_size: float, max_tiles: int = MAX_TILES) -> list[np.ndarray]:
    """Row indices of ``points`` (M, 3) in each tile of the k-d split (see the module doc)."""
    parts = [np.arange(len(points))]
    while len(parts) < max_tiles:
        ext = [np.ptp(points[p], axis=0) if len(p) > 1 else np.zeros(3) for p in parts]
        k = int(np.argmax([e.max() for e in ext]))
        if ext[k].max() <= MIN_TILE_VOXELS * voxel_size:
            break
        axis = int(np.argmax(ext[k]))
        rows = parts[k]
        order = rows[np.argsort(points[rows, axis], kind="stable")]
        half = len(order) // 2
        parts[k : k + 1] = [order[:half], order[half:]]
    return parts


def cloud_shapes(
    points: np.ndarray,
    voxel_size: float,
    base_inv: np.ndarray,
    name: str,
    max_tiles: int = MAX_TILES,
) -> list[WorldShape]:
    """World shapes (kind ``environment``) of a cloud's voxel centres (M, 3) (world frame).

    Args:
        points: Occupied voxels' centres [m] (world frame, world grid).
        voxel_size: Voxel edge [m]: the octrees' resolution.
        base_inv: Inverse of the robot base's pose in the world (4, 4).
        name: The shapes are named ``<name>_<tile>``.
        max_tiles: Most octrees.
    """
    return [
        WorldShape(f"{name}_{j}", octree(points[rows], voxel_size), base_inv, "environment")
        for j, rows in enumerate(tiles(points, voxel_size, max_tiles))
        if len(rows)
    ]


def within_distance(shape: WorldShape, points: np.ndarray, distance: float) -> np.ndarray:
    """Which points (M, 3) lie within ``distance`` [m] of a shape (its placement's frame).

    coal's distance from each point (a sphere of radius 0) to the geometry; a
    point inside a primitive is at distance 0; for a mesh, the distance to its
    surface. Points outside the shape's bounding box grown by ``distance`` are
    not queried.
    """
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    geom = shape.geometry
    geom.computeLocalAABB()
    inv = np.linalg.inv(shape.placement)
    local = pts @ inv[:3, :3].T + inv[:3, 3]
    lo = np.asarray(geom.aabb_local.min_) - distance - 1e-9
    hi = np.asarray(geom.aabb_local.max_) + distance + 1e-9
    near = np.flatnonzero(np.all((local >= lo) & (local <= hi), axis=1))
    out = np.zeros(len(pts), dtype=bool)
    if not near.size:
        return out
    probe = coal.Sphere(0.0)
    tf = coal_transform(np.eye(4))
    req, res = coal.DistanceRequest(), coal.DistanceResult()
    eye = np.eye(3)
    for i in near.tolist():
        res.clear()
        d = coal.distance(geom, tf, probe, coal.Transform3s(eye, local[i]), req, res)
        out[i] = d <= distance
    return out
