"""The robot's reach envelope: where its grasp frame can go, as an optional scene layer.

:data:`ENVELOPE_SAMPLES` configurations drawn uniformly within the joint
limits (seeded: the same on every run; a joint without finite limits spans
one turn) are put through forward kinematics; the grasp frame's positions
are drawn as faint points at ``/envelope/points`` and their convex hull as a
translucent surface at ``/envelope/hull``. The layer starts hidden (meshcat's
``visible`` property of ``/envelope`` is false): the page shows it on demand.
Collisions are not checked: it is where the arm's kinematics can reach, an
upper bound of where it can grasp.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from gcm_pipeline.outputs.meshcat_lib import load_meshcat
from gcm_pipeline.outputs.scene_glyphs import hex_color, points_object
from gcm_pipeline.robot.model import Robot

__all__ = ["ENVELOPE_COLOR", "ENVELOPE_SAMPLES", "draw_envelope", "envelope_points"]

#: Configurations sampled.
ENVELOPE_SAMPLES = 4000
#: Colour (RGB in [0, 1]) of the envelope: a pale slate, apart from every other layer.
ENVELOPE_COLOR = (0.62, 0.66, 0.74)


def envelope_points(robot: Robot, base: np.ndarray, count: int = ENVELOPE_SAMPLES) -> np.ndarray:
    """Grasp-frame positions (count, 3) in the world [m] of random configurations."""
    lo = np.where(np.isfinite(robot.lower), robot.lower, -np.pi)
    hi = np.where(np.isfinite(robot.upper), robot.upper, np.pi)
    q = np.random.default_rng(0).uniform(lo, hi, (count, robot.nq))
    pos = robot.fk(q)[:, :3, 3]
    return pos @ base[:3, :3].T + base[:3, 3]


def _hull(points: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
    """Vertices and outward triangles of the points' convex hull; None when flat."""
    from scipy.spatial import ConvexHull, QhullError

    try:
        hull = ConvexHull(points)
    except (QhullError, ValueError):
        return None
    used = np.unique(hull.simplices)
    remap = np.full(len(points), -1)
    remap[used] = np.arange(len(used))
    tris = remap[hull.simplices]
    # Qhull's simplices are not consistently wound: turn each outward
    centre = points[used].mean(axis=0)
    v = points[used]
    normal = np.cross(v[tris[:, 1]] - v[tris[:, 0]], v[tris[:, 2]] - v[tris[:, 0]])
    inward = np.einsum("ij,ij->i", normal, v[tris[:, 0]] - centre) < 0
    tris[inward] = tris[inward][:, [0, 2, 1]]
    return v, tris


def draw_envelope(vis: Any, robot: Robot, base: np.ndarray) -> dict[str, Any]:
    """Draw the reach envelope, hidden, at ``/envelope``; its layer dict."""
    mg = load_meshcat().geometry
    pts = envelope_points(robot, base)
    colors = np.tile(np.asarray(ENVELOPE_COLOR, dtype=np.float32), (len(pts), 1))
    vis["envelope/points"].set_object(points_object(pts, colors, 0.006))
    hull = _hull(pts)
    if hull is not None:
        material = mg.MeshLambertMaterial(
            color=int(hex_color(ENVELOPE_COLOR)[1:], 16),
            opacity=0.12,
            transparent=True,
            depthWrite=False,
        )
        vis["envelope/hull"].set_object(
            mg.TriangularMeshGeometry(hull[0].astype(np.float32), hull[1]), material
        )
    vis["envelope"].set_property("visible", False)
    return {
        "path": "/envelope",
        "group": "scene",
        "label": "robot reach envelope (random configurations, no collision check)",
        "color": hex_color(ENVELOPE_COLOR),
        "count": len(pts),
        "visible": False,
    }
