"""The scene's camera: where it stands and what it looks at.

:func:`frame_scene` frames the grasps with the robot and the object beside
them, looking past the arm; :func:`set_camera` places meshcat's default
camera there.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from gcm_pipeline.outputs.robot_view import ROT_X90

__all__ = ["frame_scene", "set_camera"]

_CAMERA_FOV_DEG = 75.0  # meshcat's default camera
_VIEW_DIR = np.array([1.0, 0.75, 0.55])


def frame_scene(
    grasp_points: np.ndarray,
    other_points: np.ndarray,
    robot_points: np.ndarray,
    *,
    orbit_target: bool,
) -> tuple[np.ndarray, np.ndarray]:
    """Camera target and position [m] of the scene (see :func:`_camera`).

    Without ``orbit_target`` (the live viewer: its camera looks at the world
    origin) the view direction is kept and the camera backs off from the
    origin until the scene fits.
    """
    target, position = _camera(grasp_points, other_points, robot_points)
    if not orbit_target:
        radius = float(np.max(np.linalg.norm(other_points - 0.0, axis=1), initial=0.2))
        radius = max(radius, float(np.linalg.norm(target)) + 0.2)
        direction = (position - target) / np.linalg.norm(position - target)
        target = np.zeros(3)
        position = direction * radius / math.sin(math.radians(_CAMERA_FOV_DEG) / 2.0)
    return target, position


def _camera(
    grasp_points: np.ndarray, other_points: np.ndarray, robot_points: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Camera target and position [m] framing the grasps and the other points.

    Grasp positions are trimmed to their 1st-99th percentiles (a few stray
    grasps should not shrink the view); robot and object points count fully.
    The target sits between the centre of everything and the centre of the
    grasps (they are what the scene is about); the distance fits the farthest
    point in the vertical field of view. The view direction is chosen among
    a ring of directions 30 deg above the horizon: the one whose line of sight
    to the grasps passes farthest from the robot's links (no arm in front of
    the grasps), preferring views that show robot and object side by side.
    """
    parts = [other_points]
    if len(grasp_points):
        parts.append(np.percentile(grasp_points, [1, 99], axis=0))
    pts = np.concatenate(parts)
    lo, hi = pts.min(axis=0), pts.max(axis=0)
    target = 0.5 * (lo + hi)
    focus = np.median(grasp_points, axis=0) if len(grasp_points) else target
    target = 0.5 * (target + focus)
    # + 0.08 m: the links' meshes reach beyond the joint origins that stand for them
    radius = max(float(np.max(np.linalg.norm(pts - target, axis=1))) + 0.08, 0.2)
    dist = 0.9 * radius / math.sin(math.radians(_CAMERA_FOV_DEG) / 2.0)
    direction = _view_direction(target, focus, dist, robot_points)
    return target, target + direction * dist


def _view_direction(
    target: np.ndarray, focus: np.ndarray, dist: float, robot_points: np.ndarray
) -> np.ndarray:
    default = _VIEW_DIR / np.linalg.norm(_VIEW_DIR)
    if len(robot_points) < 2:
        return default
    # sample the links: joint origins and the midpoints between consecutive ones
    links = np.concatenate([robot_points, 0.5 * (robot_points[1:] + robot_points[:-1])])
    side = focus[:2] - robot_points[0, :2]
    side = side / (np.linalg.norm(side) + 1e-12)
    best, best_score = default, -np.inf
    elev = math.radians(30.0)
    for az in np.radians(np.arange(0.0, 360.0, 20.0)):
        d = np.array([math.cos(az) * math.cos(elev), math.sin(az) * math.cos(elev), math.sin(elev)])
        eye = target + d * dist
        seg = focus - eye
        t = np.clip(((links - eye) @ seg) / (seg @ seg), 0.0, 1.0)
        clearance = float(np.min(np.linalg.norm(eye + t[:, None] * seg - links, axis=1)))
        eye_clearance = float(np.min(np.linalg.norm(links - eye, axis=1)))
        across = abs(d[0] * side[1] - d[1] * side[0]) / math.cos(elev)
        score = (
            min(clearance, 0.2)
            + 0.3 * min(eye_clearance, 0.6)
            + 0.08 * across
            + 0.02 * float(d @ default)
        )
        if score > best_score:
            best, best_score = d, score
    return best


def set_camera(vis: Any, position: np.ndarray) -> None:
    """Place meshcat's default camera at ``position`` (world, [m]).

    The camera hangs under ``/Cameras/default/rotated``, whose rotation undoes
    the viewer's z-up to y-up turn of the scene, so the camera's local
    coordinates are three.js world coordinates: ``R_x(90 deg)^T @ world``.
    meshcat 0.3 has no command for the orbit target (the static page sets
    ``viewer.controls.target``, :mod:`gcm_pipeline.outputs.html`); without it the camera
    looks at the world origin.
    """
    vis["/Cameras/default"].set_transform(np.eye(4))
    local = ROT_X90.T @ np.asarray(position, dtype=float)
    vis["/Cameras/default/rotated/<object>"].set_property("position", local.tolist())
