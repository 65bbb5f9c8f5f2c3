"""Scene point clouds and grasp contact points as meshcat points.

A :class:`SceneCloud` is the plain value the scene takes for a point cloud
(``gcm_pipeline.pipeline`` maps a run's processed clouds onto it): points in
the world frame with optional colours and segment ids. :func:`draw_clouds`
draws each cloud as one meshcat ``Points`` object under ``/cloud/<name>``,
coloured by its RGB when it has one, else by segment, else by height, and
subsampled to at most :data:`MAX_CLOUD_POINTS` points over all clouds (a
uniform random subset, the same on every run) so that the page stays light
and the viewer responsive. :func:`draw_contacts` draws the grasps' contact
points (``contact_x``, ``contact_y``, ``contact_z``) as one ``Points``
object at ``/contacts``.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from gcm_pipeline.errors import PublishError
from gcm_pipeline.outputs.meshcat_lib import load_meshcat
from gcm_pipeline.outputs.plots import colormap
from gcm_pipeline.table import GraspTable

__all__ = [
    "CONTACT_COLOR",
    "MAX_CLOUD_POINTS",
    "SceneCloud",
    "cloud_corners",
    "contact_points",
    "draw_clouds",
    "draw_contacts",
]

#: Most cloud points drawn, over all clouds: 2.4 MB of positions and colours, a 4 MB page.
MAX_CLOUD_POINTS = 100_000
#: Colour (RGB in [0, 1]) of the contact points: magenta, apart from the glyphs' viridis.
CONTACT_COLOR = (1.0, 0.0, 1.0)
#: Edge of a contact point's square on screen, in world units [m].
CONTACT_SIZE = 0.012
_CONTACT_COLUMNS = ("contact_x", "contact_y", "contact_z")


@dataclass(frozen=True, eq=False)
class SceneCloud:
    """A point cloud in the world, as the scene draws it.

    Attributes:
        points: (N, 3) positions in the world [m].
        colors: (N, 3) uint8 RGB, or None.
        segments: (N,) integer segment ids, or None.
        name: Scene path under ``/cloud`` (letters, digits, ``_``, ``-``).
        point_size: Edge of a point's square, in world units [m] (the voxel size).
    """

    points: np.ndarray
    colors: np.ndarray | None = None
    segments: np.ndarray | None = None
    name: str = "cloud"
    point_size: float = 0.005

    def __post_init__(self) -> None:
        pts = np.asarray(self.points, dtype=float).reshape(-1, 3)
        n = len(pts)
        for key, width in (("colors", 3), ("segments", None)):
            value = getattr(self, key)
            if value is None:
                continue
            shape = np.shape(value)
            if shape[:1] != (n,) or (width is not None and shape[1:] != (width,)):
                raise PublishError(
                    f"point cloud {self.name!r}: {key} has shape {shape}, points has {n} rows"
                )
        object.__setattr__(self, "points", pts)


def _subset(sizes: Sequence[int], budget: int) -> list[np.ndarray]:
    """Row indices kept of each cloud: all when they fit, else a share of ``budget`` each."""
    total = sum(sizes)
    rng = np.random.default_rng(0)
    out = []
    for n in sizes:
        keep = n if total <= budget else int(budget * n // total)
        out.append(np.arange(n) if keep >= n else np.sort(rng.choice(n, size=keep, replace=False)))
    return out


def _colors(cloud: SceneCloud, rows: np.ndarray) -> np.ndarray:
    """(M, 3) float32 colours in [0, 1]: RGB, else one per segment, else by height."""
    if cloud.colors is not None:
        return np.asarray(cloud.colors, dtype=np.float32)[rows] / 255.0
    if cloud.segments is not None and len(np.unique(cloud.segments)) > 1:
        ids = np.unique(cloud.segments, return_inverse=True)[1][rows]
        return np.asarray(colormap("tab10")(ids % 10)[:, :3], dtype=np.float32)
    z = cloud.points[rows, 2]
    lo, hi = (float(z.min()), float(z.max())) if len(z) else (0.0, 1.0)
    t = (z - lo) / (hi - lo) if hi > lo else np.zeros_like(z)
    return np.asarray(colormap("viridis")(t)[:, :3], dtype=np.float32)


def _points(vertices: np.ndarray, colors: np.ndarray, size: float) -> Any:
    mg = load_meshcat().geometry
    geometry = mg.PointsGeometry(
        np.ascontiguousarray(vertices.T, dtype=np.float32),
        np.ascontiguousarray(colors.T, dtype=np.float32),
    )
    return mg.Points(geometry, mg.PointsMaterial(size=float(size)))


def draw_clouds(
    vis: Any, clouds: Sequence[SceneCloud], budget: int = MAX_CLOUD_POINTS
) -> tuple[list[str], dict[str, int]]:
    """Draw each cloud at ``/cloud/<name>``, at most ``budget`` points over all of them.

    Returns:
        The scene paths drawn (``["/cloud"]`` or none) and the points drawn per cloud name.
    """
    drawn: dict[str, int] = {}
    for cloud, rows in zip(clouds, _subset([len(c.points) for c in clouds], budget), strict=True):
        if not len(rows):
            continue
        obj = _points(cloud.points[rows], _colors(cloud, rows), cloud.point_size)
        vis[f"cloud/{cloud.name}"].set_object(obj)
        drawn[cloud.name] = len(rows)
    return (["/cloud"] if drawn else []), drawn


def contact_points(grasps: GraspTable) -> np.ndarray:
    """(M, 3) finite contact points of the table's rows (none without the columns)."""
    if not all(k in grasps for k in _CONTACT_COLUMNS):
        return np.zeros((0, 3))
    pts = np.column_stack([np.asarray(grasps[k], dtype=float) for k in _CONTACT_COLUMNS])
    return pts[np.all(np.isfinite(pts), axis=1)]


def draw_contacts(vis: Any, grasps: GraspTable) -> tuple[list[str], int]:
    """Draw the grasps' contact points at ``/contacts``; the paths drawn and the count."""
    pts = contact_points(grasps)
    if not len(pts):
        return [], 0
    colors = np.tile(np.asarray(CONTACT_COLOR, dtype=np.float32), (len(pts), 1))
    vis["contacts"].set_object(_points(pts, colors, CONTACT_SIZE))
    return ["/contacts"], len(pts)


def cloud_corners(clouds: Sequence[SceneCloud]) -> np.ndarray:
    """(8 K, 3) corners of the clouds' bounding boxes, for framing the camera."""
    out = []
    for c in clouds:
        if len(c.points):
            lo, hi = c.points.min(axis=0), c.points.max(axis=0)
            out.append(np.array([[(lo, hi)[(k >> i) & 1][i] for i in range(3)] for k in range(8)]))
    return np.concatenate(out) if out else np.zeros((0, 3))
