"""coal's distance of a robot geometry to a cloud's octree, over the cells that can matter.

coal's octree distance traverses the whole tree against the geometry's
bounding volumes (tens of milliseconds for a tile of a few thousand 5 mm cells,
and it grows with the tile). The clearance only needs a pair's distance when it
is below a cap (the best distance of the row so far): a cell can be that near
only when its centre lies within ``r + cap + reach`` of one of the geometry's
cover spheres (radius ``r``; ``reach``, the cell's half diagonal), since the
spheres hold the geometry. :func:`near_distance` gives coal those cells alone,
as an octree of the same resolution on the same grid (its leaves are the same
boxes, so coal evaluates the same box-triangle distances), and returns coal's
answer: equal to the whole tile's wherever that is below the cap, and above the
cap where the whole tile's is (the tests compare both on sampled configurations).
A penetration (a distance <= 0) is answered by the whole tile.

The cap is also bounded by a point of the geometry (a hull vertex) and its
nearest cell centre, so the first pair of a row needs no cap of its own.
"""

from __future__ import annotations

from typing import Any

import coal
import numpy as np

__all__ = ["CAP_SLACK", "near_distance"]

#: Added to every cell's search radius [m]: coal's distances differ from the exact
#: ones by its GJK tolerance (1e-6 m), so a cell a little beyond the cap is kept.
CAP_SLACK = 1e-5


def near_distance(
    geometry: Any,
    geometry_tf: Any,
    tree: Any,
    tree_tf: Any,
    cells: Any,
    reach: float,
    centres: np.ndarray,
    radii: np.ndarray,
    points: np.ndarray,
    cap: float,
    request: Any,
) -> float:
    """The distance [m] by coal of ``geometry`` to ``tree`` wherever it is below ``cap``.

    Args:
        geometry: The robot's coal geometry.
        geometry_tf: Its placement (``coal.Transform3s``).
        tree: The coal ``OcTree``.
        tree_tf: Its placement.
        cells: A ``cKDTree`` of the tree's occupied cell centres (the tree's frame).
        reach: The largest cell's half diagonal [m] (:func:`~.broadphase.octree_cells`).
        centres: The geometry's cover spheres' centres (S, 3), in the tree's frame.
        radii: Their radii (S,) [m].
        points: Points of the geometry (V, 3) (its hull vertices), in the tree's frame.
        cap: Distances at or above it may be answered by any value at or above it [m].
        request: The pair's ``coal.DistanceRequest``.

    Returns:
        coal's distance over the cells within reach of the cap; ``inf`` when none is;
        coal's over the whole tree for a penetration or a tree without cells.
    """
    if reach <= 0.0:  # no occupied cell (octree_cells' stand-in far point): coal decides
        return _whole(geometry, geometry_tf, tree, tree_tf, request)
    if len(points):
        cap = min(cap, float(np.min(cells.query(points)[0])))
    if not np.isfinite(cap):
        return _whole(geometry, geometry_tf, tree, tree_tf, request)
    near = cells.query_ball_point(centres, radii + (cap + reach + CAP_SLACK))
    rows = np.sort(np.concatenate([np.asarray(r, dtype=np.intp) for r in near]))
    if rows.size == 0:
        return np.inf
    rows = rows[np.concatenate(([True], rows[1:] != rows[:-1]))]  # np.unique's, by a sort
    sub = coal.makeOctree(np.ascontiguousarray(cells.data[rows]), tree.getResolution())
    result = coal.DistanceResult()
    d = float(coal.distance(geometry, geometry_tf, sub, tree_tf, request, result))
    if d <= 0.0:  # a penetration: coal's depth comes from the whole tree's traversal
        return _whole(geometry, geometry_tf, tree, tree_tf, request)
    return d


def _whole(geometry: Any, geometry_tf: Any, tree: Any, tree_tf: Any, request: Any) -> float:
    """The distance by coal of ``geometry`` to the whole ``tree``."""
    return float(
        coal.distance(geometry, geometry_tf, tree, tree_tf, request, coal.DistanceResult())
    )
