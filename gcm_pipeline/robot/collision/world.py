"""The collision world: coal geometries placed in the robot's base frame.

The world is a list of :class:`WorldShape` objects: the support table and
obstacles (kind ``environment``) and the object being grasped (kind
``object``). :func:`table_shape`, :func:`obstacle_shape` and
:func:`object_shape` build them from plain sizes, poses and shapes (the
shape -> geometry table is :mod:`gcm_pipeline.geometry.shapes`); the run's
config is mapped onto them in :mod:`gcm_pipeline.pipeline`.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import coal
import numpy as np

from gcm_pipeline.errors import ConfigError, InputError, choice_error
from gcm_pipeline.geometry.shapes import shape_geometry
from gcm_pipeline.robot.collision.contact import erode_convex

__all__ = [
    "ENVIRONMENT_SHAPES",
    "PRIMITIVES",
    "WorldShape",
    "as_transform",
    "depth_into",
    "erode_primitive",
    "object_shape",
    "obstacle_shape",
    "table_shape",
]

#: Shapes an obstacle may have (a plane is an object only).
ENVIRONMENT_SHAPES = ("box", "cylinder", "sphere", "mesh")
#: Coal geometries eroded exactly (:func:`erode_primitive`).
PRIMITIVES = (coal.Box, coal.Sphere, coal.Cylinder)


@dataclass(frozen=True)
class WorldShape:
    """A collision shape of the world, placed in the robot's base frame.

    Attributes:
        name: Geometry name (``table``, ``obstacle_<i>`` or the obstacle's name, ``object``).
        geometry: The coal geometry (centred as coal defines it).
        placement: Pose of the geometry's centre in the base frame (4, 4) [m].
        kind: ``"environment"`` or ``"object"`` (at most one object).
        support: The robot's base stands on it (the table): base links that
            touch it in the home configuration are not checked against it.
    """

    name: str
    geometry: Any
    placement: np.ndarray
    kind: str
    support: bool = False


def as_transform(pose: Any) -> np.ndarray:
    """A pose as a (4, 4) homogeneous transform (identity for None).

    Args:
        pose: A (4, 4) array, an object with a ``matrix()`` method (a config
            ``Pose``) or None.

    Returns:
        (4, 4) transform [m].

    Raises:
        InputError: If an array is not (4, 4) or not finite.
    """
    if pose is None:
        return np.eye(4)
    if hasattr(pose, "matrix"):
        return np.asarray(pose.matrix(), dtype=float)
    arr = np.asarray(pose, dtype=float)
    if arr.shape != (4, 4) or not np.all(np.isfinite(arr)):
        raise InputError(f"a pose must be a finite (4, 4) transform, got shape {arr.shape}")
    return arr


def table_shape(
    size: Any, center_xy: Any, height: float, base_inv: np.ndarray, where: str = "environment.table"
) -> WorldShape:
    """The support table: a box whose top face is at ``height``, centred at ``center_xy``.

    Args:
        size: Box sizes (x, y, z) [m].
        center_xy: Centre of the top face in the world (x, y) [m].
        height: Height of the top face in the world [m].
        base_inv: Inverse of the robot base's pose in the world (4, 4).
        where: Config location used in error messages.

    Returns:
        The ``table`` shape (kind ``environment``, the robot's support).

    Raises:
        ConfigError: A size that is not a positive number.
    """
    for s in size:
        if not np.isfinite(s) or s <= 0:
            raise ConfigError(f"{where}: size must be positive numbers [m], got {s!r}")
    sx, sy, sz = (float(s) for s in size)
    m = np.eye(4)
    m[:3, 3] = (center_xy[0], center_xy[1], height - 0.5 * sz)
    return WorldShape("table", coal.Box(sx, sy, sz), base_inv @ m, "environment", support=True)


def obstacle_shape(
    name: str,
    shape: str,
    dims: Any,
    pose: np.ndarray,
    base_inv: np.ndarray,
    *,
    mesh: Path | None = None,
    scale: float = 1.0,
    where: str = "obstacle",
) -> WorldShape:
    """An obstacle (kind ``environment``), placed like the object.

    A cylinder stands on its base along its frame's z, boxes and spheres are
    centred on their frame (:func:`~gcm_pipeline.geometry.shapes.shape_geometry`).

    Args:
        name: Shape name.
        shape: One of :data:`ENVIRONMENT_SHAPES`.
        dims: An object with ``radius``, ``height``, ``size``.
        pose: The shape's frame in the world (4, 4) [m].
        base_inv: Inverse of the robot base's pose in the world (4, 4).
        mesh: Mesh file (shape ``mesh``).
        scale: Mesh scale factor.
        where: Config location used in error messages.

    Raises:
        ConfigError: Unknown shape, missing or non-positive size.
        InputError: A mesh file is missing or unreadable (the message names it).
    """
    if shape not in ENVIRONMENT_SHAPES:
        raise choice_error(ConfigError, "shape", shape, ENVIRONMENT_SHAPES, prefix=f"{where}: ")
    made = shape_geometry(shape, dims, mesh=mesh, scale=scale, where=where)
    assert made is not None
    geom, centre = made
    return WorldShape(name, geom, base_inv @ pose @ centre, "environment")


def object_shape(
    shape: str,
    dims: Any,
    pose: np.ndarray,
    base_inv: np.ndarray,
    *,
    mesh: Path | None = None,
    scale: float = 1.0,
    where: str = "object",
) -> WorldShape:
    """The object being grasped (kind ``object``), named ``object``.

    Args: as :func:`obstacle_shape` (any shape of
    :data:`~gcm_pipeline.geometry.shapes.SHAPES`).

    Raises:
        ConfigError: Unknown shape, missing or non-positive size.
        InputError: A mesh file is missing or unreadable (the message names it).
    """
    made = shape_geometry(shape, dims, mesh=mesh, scale=scale, where=where)
    assert made is not None
    return WorldShape("object", made[0], base_inv @ pose @ made[1], "object")


def depth_into(shape: WorldShape, support: WorldShape) -> float:
    """How deep [m] ``shape`` reaches into the box ``support`` (0: apart or touching).

    coal's penetration depth (its signed distance) for a primitive; for a mesh,
    whose distance stops at 0, the depth of its lowest vertex under the box's
    top face (the box's +z face: the table's top).
    """
    req = coal.DistanceRequest()
    req.enable_signed_distance = True
    a, b = shape.placement, support.placement
    d = coal.distance(
        shape.geometry,
        coal.Transform3s(a[:3, :3], a[:3, 3]),
        support.geometry,
        coal.Transform3s(b[:3, :3], b[:3, 3]),
        req,
        coal.DistanceResult(),
    )
    if d > 0.0:
        return 0.0
    if not isinstance(shape.geometry, coal.BVHModelBase):
        return float(-d)
    verts = np.asarray(shape.geometry.vertices(), dtype=float).reshape(-1, 3)
    verts = verts @ a[:3, :3].T + a[:3, 3]
    top = (b[:3, 3] + b[:3, 2] * float(support.geometry.halfSide[2])) @ b[:3, 2]
    return max(0.0, float(top - (verts @ b[:3, 2]).min()))


def depth_below(shape: WorldShape, height: float) -> float:
    """How far [m] the lowest point of ``shape`` lies below the plane z = ``height`` (0: above).

    Exact: coal's signed distance to the half-space under the plane for a primitive,
    the lowest vertex for a mesh.
    """
    a = shape.placement
    if isinstance(shape.geometry, coal.BVHModelBase):
        verts = np.asarray(shape.geometry.vertices(), dtype=float).reshape(-1, 3)
        return max(0.0, float(height - (verts @ a[2, :3] + a[2, 3]).min()))
    req = coal.DistanceRequest()
    req.enable_signed_distance = True
    d = coal.distance(
        shape.geometry,
        coal.Transform3s(a[:3, :3], a[:3, 3]),
        coal.Halfspace(np.array([0.0, 0.0, 1.0]), float(height)),
        coal.Transform3s(),
        req,
        coal.DistanceResult(),
    )
    return max(0.0, float(-d))


def lift_out_of(shape: WorldShape, support: WorldShape, most: float) -> float:
    """How far [m] ``shape`` must rise along z to leave the box ``support`` (0: apart).

    Only the part of ``shape`` over or in the box counts (a part beside it may hang
    lower): bisection on coal's distance over ``[0, most]`` (to about 1e-6 m, coal's
    GJK tolerance), ``most`` a lift known to clear it (e.g. :func:`depth_below` the
    box's top, plus that tolerance).
    """
    b, a = support.placement, shape.placement
    box = coal.Transform3s(b[:3, :3], b[:3, 3])
    req = coal.DistanceRequest()

    def apart(t: float) -> bool:
        at = coal.Transform3s(a[:3, :3], a[:3, 3] + np.array([0.0, 0.0, t]))
        return (
            coal.distance(shape.geometry, at, support.geometry, box, req, coal.DistanceResult()) > 0
        )

    if apart(0.0):
        return 0.0
    lo, hi = 0.0, float(most)
    while hi - lo > 1e-9:
        mid = 0.5 * (lo + hi)
        lo, hi = (lo, mid) if apart(mid) else (mid, hi)
    return hi


def erode_primitive(geometry: Any, distance: float) -> Any | None:
    """A coal primitive shrunk by ``distance`` [m] on every side (exact), or None.

    Boxes, spheres and cylinders are eroded exactly; None when nothing is left
    (a part thinner than ``2 * distance``) or for any other geometry (meshes:
    the gripper is eroded instead, see :mod:`gcm_pipeline.robot.collision.contact`).
    """
    if isinstance(geometry, PRIMITIVES):
        return erode_convex(geometry, distance)
    return None
