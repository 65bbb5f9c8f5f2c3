"""One shape -> coal geometry table: the shapes of a run's object and obstacles.

A shape is named (``box``, ``cylinder``, ``sphere``, ``plane``, ``mesh``) and
sized by an object with ``radius``, ``height`` and ``size`` (a config's
``dims``); :func:`shape_geometry` gives its coal geometry and the pose of the
geometry's centre in the shape's frame. The collision world
(:mod:`gcm_pipeline.robot.collision.world`) builds the support table, the
obstacles and the object from it.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import coal
import numpy as np

from gcm_pipeline.errors import ConfigError, InputError, choice_error
from gcm_pipeline.geometry.meshes import MeshReadError, read_mesh

__all__ = ["PLANE_THICKNESS", "SHAPES", "shape_geometry"]

SHAPES = ("cylinder", "box", "sphere", "plane", "mesh")
PLANE_THICKNESS = 0.002  # [m] a 'plane' object is a box this thick, centred on its frame


def _load_mesh(path: Path | None, scale: float, where: str) -> Any:
    if path is None:
        raise ConfigError(f"{where}: shape 'mesh' needs 'mesh: <path>'")
    try:
        return read_mesh(path, scale)
    except MeshReadError as exc:
        raise InputError(f"{where}: {exc}") from exc


def _positive(where: str, name: str, value: float | None) -> float:
    if value is None or not math.isfinite(value) or value <= 0:
        raise ConfigError(f"{where}: {name} must be a positive number [m], got {value!r}")
    return float(value)


def shape_geometry(
    shape: str,
    dims: Any,
    *,
    mesh: Path | None = None,
    scale: float = 1.0,
    erode: float = 0.0,
    where: str = "shape",
) -> tuple[Any, np.ndarray] | None:
    """Coal geometry of a config shape and the offset of its centre in the shape's frame.

    Conventions (those of the config's ``object``): a cylinder stands on its base with
    its axis along the frame's z (base at z = 0); boxes and spheres are centred
    on the frame origin; a plane is a :data:`PLANE_THICKNESS` thick box centred on
    the frame's xy plane; a mesh is used as its file defines it (times ``scale``).

    Args:
        shape: ``box``, ``cylinder``, ``sphere``, ``plane`` or ``mesh``.
        dims: An object with ``radius``, ``height``, ``size`` (the config's ``dims``).
        mesh: Mesh file (shape ``mesh``).
        scale: Mesh scale factor.
        erode: Distance [m] by which a primitive shrinks on every side (0: the shape
            itself). Meshes are not eroded (the gripper is, see
            :mod:`gcm_pipeline.robot.collision.contact`): ``erode > 0`` with a mesh is a ValueError.
        where: Config location used in error messages.

    Returns:
        ``(geometry, centre)`` with ``centre`` (4, 4) the geometry's pose in the
        shape's frame; None when erosion leaves nothing (a part thinner than
        ``2 * erode``).

    Raises:
        ConfigError: Unknown shape, missing or non-positive size.
        InputError: Mesh file missing or unreadable (names the file).
    """
    centre = np.eye(4)
    if shape == "cylinder":
        radius = _positive(where, "dims.radius", dims.radius) - erode
        height = _positive(where, "dims.height", dims.height)
        centre[2, 3] = 0.5 * height
        height -= 2 * erode
        if radius <= 0 or height <= 0:
            return None
        return coal.Cylinder(radius, height), centre
    if shape in ("box", "plane"):
        want = 3 if shape == "box" else 2
        size = tuple(dims.size or ())
        if len(size) != want:
            raise ConfigError(f"{where}: shape {shape!r} needs dims.size with {want} values")
        sizes = [_positive(where, "dims.size", s) for s in size]
        if shape == "plane":
            sizes.append(PLANE_THICKNESS)
        eroded = [s - 2 * erode for s in sizes]
        if min(eroded) <= 0:
            return None
        return coal.Box(*eroded), centre
    if shape == "sphere":
        radius = _positive(where, "dims.radius", dims.radius) - erode
        if radius <= 0:
            return None
        return coal.Sphere(radius), centre
    if shape == "mesh":
        if erode > 0:
            raise ValueError(
                "a mesh is not eroded: the gripper's pieces are "
                "(gcm_pipeline.robot.collision.contact)"
            )
        _positive(where, "scale", scale)
        return _load_mesh(mesh, scale, where), centre
    raise choice_error(ConfigError, "shape", shape, SHAPES, prefix=f"{where}: ")
