"""Grasp generators: grasp frames placed on a primitive object, standing in for a synthesiser.

The generators stand in for a grasp synthesiser. Each places ``count`` grasp
frames on the object described by the config's ``object`` section, in the
object frame, adds seeded noise and maps the poses into the world by the
object pose. A grasp pose is the pose of the robot's grasp frame
(``panda_hand_tcp`` for the Panda): origin between the fingertips, z = the
approach direction, fingers closing along y.

========================= ===================================================
source                    grasps
========================= ===================================================
``plane``                 on a flat surface (the paper's Fig. 1): positions
                          uniform in the plane's ``size``, approach from above
                          (z pointing down, along the plane's -z), a random yaw
                          in [-45, 45] deg about the approach
``cylinder_side``         a bottle grasped along its side: ``rings`` rings at
                          heights in [0.2, 0.8] of the cylinder's height
                          (default: as many as give an even spacing),
                          staggered evenly spaced angles, approach radial
                          (z toward the axis), fingers closing tangentially
                          (y along the tangent), x along the cylinder axis
``box``                   on the five faces other than the one the box stands
                          on (its frame's -z face), chosen with probability
                          proportional to their area; approach along the
                          inward face normal, fingers closing along the
                          face's shorter side, near the face's middle line
``sphere``                a Fibonacci lattice over the sphere without its
                          bottom cap (polar angle <= 120 deg); approach toward
                          the centre, fingers closing along the horizontal
                          tangent
========================= ===================================================

``depth`` [m] moves every generated grasp frame along its approach axis,
past the surface (default 0 for ``plane``, 0.01 m otherwise: the fingertips
reach 1 cm past the surface they approach).

Noise: ``noise.position`` [m] is the standard deviation of a Gaussian
displacement per world axis; ``noise.angle_deg`` [deg] the standard deviation
of the angle of a rotation about a uniformly random axis, applied in the grasp
frame (on the right). All randomness comes from one
:func:`numpy.random.default_rng` seeded by ``candidates.seed`` (or the top-level
``seed``), so the same config gives the same candidates.

Generated grasps (and the ``antipodal`` sampler's) are mapped by ``grasp_to_tool``
on the right before the object pose, ``T_world = T_object @ T_grasp @
grasp_to_tool``: the generators make the frame of a Panda-like TCP (z =
approach, fingers closing along y, origin between the fingertips), which
another tool may need offset or turned.

Everything is vectorised: poses are (N, 4, 4) arrays until they become the
``dq`` column of a :class:`~gcm_pipeline.table.GraspTable`.
"""

from __future__ import annotations

import math

import numpy as np
from scipy.spatial.transform import Rotation

from gcm_pipeline.errors import ConfigError

__all__ = [
    "DEFAULT_DEPTH",
    "GENERATORS",
    "add_noise",
    "generate",
    "poses_box",
    "poses_cylinder_side",
    "poses_plane",
    "poses_sphere",
]

#: The generators (``candidates.source``) and the object shape each needs.
GENERATORS = {"plane": "plane", "cylinder_side": "cylinder", "box": "box", "sphere": "sphere"}

#: Default ``depth`` [m] per generator.
DEFAULT_DEPTH = {"plane": 0.0, "cylinder_side": 0.01, "box": 0.01, "sphere": 0.01}


def _frames(x: np.ndarray, y: np.ndarray, z: np.ndarray, p: np.ndarray) -> np.ndarray:
    """Stack axis columns (N, 3) and positions (N, 3) into (N, 4, 4) transforms."""
    n = p.shape[0]
    t = np.zeros((n, 4, 4))
    t[:, :3, 0] = x
    t[:, :3, 1] = y
    t[:, :3, 2] = z
    t[:, :3, 3] = p
    t[:, 3, 3] = 1.0
    return t


def poses_plane(
    count: int, size: tuple[float, float], rng: np.random.Generator, *, depth: float = 0.0
) -> np.ndarray:
    """Grasps from above on a plane (the object's xy plane), in the object frame.

    Args:
        count: Number of grasps N.
        size: Plane extent (x, y) [m], centred on the origin; positions are
            uniform in the central 80 %.
        rng: Random generator (positions and yaw).
        depth: Offset along the approach (down, -z) [m].

    Returns:
        (N, 4, 4) grasp frames: z = (0, 0, -1), yaw uniform in [-45, 45] deg.
    """
    half = 0.4 * np.asarray(size, dtype=float)
    xy = rng.uniform(-half, half, size=(count, 2))
    yaw = rng.uniform(-math.pi / 4, math.pi / 4, size=count)
    c, s = np.cos(yaw), np.sin(yaw)
    zeros = np.zeros(count)
    # Rx(pi) @ Rz(yaw): z points down, x and y rotated by the yaw.
    x = np.stack([c, -s, zeros], axis=1)
    y = np.stack([-s, -c, zeros], axis=1)
    z = np.tile([0.0, 0.0, -1.0], (count, 1))
    p = np.column_stack([xy, np.full(count, -depth)])
    return _frames(x, y, z, p)


def poses_cylinder_side(
    count: int, radius: float, height: float, *, rings: int | None = None, depth: float = 0.01
) -> np.ndarray:
    """Side grasps on a standing cylinder (axis = object z, base at z = 0).

    The grasps lie on ``rings`` rings at heights evenly spread over
    [0.2, 0.8] * ``height``; each ring holds an even share of the grasps at
    evenly spaced angles, odd rings turned by half a step (a staggered lattice
    triangulates well in the cylindrical chart).

    Args:
        count: Number of grasps N.
        radius: Cylinder radius [m].
        height: Cylinder height [m].
        rings: Number of rings (default: as many as make the spacing of the
            rings equal to the spacing along a ring, in the cylindrical chart).
        depth: How far the grasp frame lies inside the surface [m]; the frame
            sits at distance ``radius - depth`` from the axis.

    Returns:
        (N, 4, 4) grasp frames: z = toward the axis, y = tangent
        (counter-clockwise), x = the cylinder axis (up).
    """
    rho = radius - depth
    if rings is None:
        # spacing along a ring (2 pi rho / per ring) equal to the spacing of the
        # rings (0.6 h / (rings - 1)): rings (rings - 1) = 0.6 h N / (2 pi rho)
        x = 0.6 * height * count / (2 * math.pi * max(rho, 1e-9))
        rings = max(1, round(0.5 + math.sqrt(0.25 + x)))
    rings = min(rings, count)
    ring = np.arange(count) * rings // count  # ring index of each grasp, sorted
    per_ring = np.bincount(ring, minlength=rings)
    first = np.concatenate([[0], np.cumsum(per_ring)[:-1]])
    k = np.arange(count) - first[ring]
    theta = 2 * math.pi * (k + 0.5 * (ring % 2)) / per_ring[ring]
    if rings == 1:
        h = np.full(count, 0.5 * height)
    else:
        h = height * (0.2 + 0.6 * ring / (rings - 1))
    c, s = np.cos(theta), np.sin(theta)
    zeros = np.zeros(count)
    radial = np.stack([c, s, zeros], axis=1)
    tangent = np.stack([-s, c, zeros], axis=1)
    axis = np.tile([0.0, 0.0, 1.0], (count, 1))
    p = radial * rho
    p[:, 2] = h
    return _frames(axis, tangent, -radial, p)


# Faces of a box: (outward normal axis, sign); the -z face (the one the box
# stands on) is left out.
_BOX_FACES = ((0, 1.0), (0, -1.0), (1, 1.0), (1, -1.0), (2, 1.0))


def poses_box(
    count: int, size: tuple[float, float, float], rng: np.random.Generator, *, depth: float = 0.01
) -> np.ndarray:
    """Face grasps on a box centred on the origin.

    Each grasp picks one of the faces +x, -x, +y, -y, +z with probability
    proportional to its area and a position uniform in the face's central
    20 % across the closing axis and 80 % along the other side (the open
    fingers must clear the box); the frame approaches along the inward face
    normal and the fingers close along the face's shorter side.

    Args:
        count: Number of grasps N.
        size: Box edge lengths (x, y, z) [m].
        rng: Random generator (faces and positions).
        depth: Offset past the face along the approach [m].

    Returns:
        (N, 4, 4) grasp frames in the box frame.
    """
    size_arr = np.asarray(size, dtype=float)
    eye = np.eye(3)
    areas = np.array([np.prod(np.delete(size_arr, ax)) for ax, _ in _BOX_FACES])
    face = rng.choice(len(_BOX_FACES), size=count, p=areas / areas.sum())
    # across the fingers' closing axis stay near the middle (the open fingers
    # must clear the box on both sides); along the face's other side spread out
    uv = rng.uniform(-1.0, 1.0, size=(count, 2)) * [0.1, 0.4]
    x = np.empty((count, 3))
    y = np.empty((count, 3))
    z = np.empty((count, 3))
    p = np.empty((count, 3))
    for f, (ax, sign) in enumerate(_BOX_FACES):
        sel = face == f
        normal = sign * eye[ax]
        a, b = (i for i in range(3) if i != ax)
        # fingers close along the shorter in-plane side
        close, other = (a, b) if size_arr[a] <= size_arr[b] else (b, a)
        z[sel] = -normal
        y[sel] = eye[close]
        x[sel] = np.cross(eye[close], -normal)
        p[sel] = normal * (0.5 * size_arr[ax] - depth)
        p[sel, close] = uv[sel, 0] * size_arr[close]
        p[sel, other] = uv[sel, 1] * size_arr[other]
    return _frames(x, y, z, p)


def poses_sphere(count: int, radius: float, *, depth: float = 0.01) -> np.ndarray:
    """Grasps on a sphere centred on the origin, from a Fibonacci lattice.

    Args:
        count: Number of grasps N.
        radius: Sphere radius [m].
        depth: Offset past the surface along the approach [m].

    Returns:
        (N, 4, 4) grasp frames: z toward the centre, y horizontal (the local
        "east" tangent; +y of the object frame at the top pole).
    """
    # polar angle from the top pole, cos uniform over [cos(120 deg), 1]
    i = np.arange(count) + 0.5
    cos_lo = math.cos(math.radians(120.0))
    cz = 1.0 - (1.0 - cos_lo) * i / count
    sz = np.sqrt(np.clip(1.0 - cz**2, 0.0, None))
    phi = math.pi * (3.0 - math.sqrt(5.0)) * np.arange(count)
    normal = np.stack([sz * np.cos(phi), sz * np.sin(phi), cz], axis=1)
    east = np.cross([0.0, 0.0, 1.0], normal)
    norm = np.linalg.norm(east, axis=1, keepdims=True)
    east = np.where(norm > 1e-9, east / np.maximum(norm, 1e-12), [0.0, 1.0, 0.0])
    z = -normal
    x = np.cross(east, z)
    p = normal * (radius - depth)
    return _frames(x, east, z, p)


def add_noise(
    poses: np.ndarray, position: float, angle_deg: float, rng: np.random.Generator
) -> None:
    """Perturb (N, 4, 4) poses in place: Gaussian position, random-axis rotation."""
    n = poses.shape[0]
    if position > 0:
        poses[:, :3, 3] += rng.normal(0.0, position, size=(n, 3))
    if angle_deg > 0:
        axis = rng.normal(size=(n, 3))
        axis /= np.linalg.norm(axis, axis=1, keepdims=True)
        angle = rng.normal(0.0, math.radians(angle_deg), size=(n, 1))
        poses[:, :3, :3] = poses[:, :3, :3] @ Rotation.from_rotvec(axis * angle).as_matrix()


def _check_depth(depth: float, limit: float, what: str) -> None:
    """Reject a depth past the object's centre (``depth == limit`` puts it on the centre)."""
    if depth > limit:
        raise ConfigError(
            f"candidates.depth {depth:g} m puts the grasps past the object's centre: "
            f"it must not exceed the {what} ({limit:g} m)"
        )


def generate(
    source: str,
    count: int,
    rng: np.random.Generator,
    *,
    shape: str | None,
    radius: float | None = None,
    height: float | None = None,
    size: tuple[float, ...] | None = None,
    depth: float | None = None,
    rings: int | None = None,
) -> np.ndarray:
    """Poses (N, 4, 4) of generator ``source`` on the object, in the object frame.

    Args:
        source: One of :data:`GENERATORS` (``candidates.source``).
        count: Number of grasps N.
        rng: Random generator (the generators that draw; the noise draws after).
        shape: The object's shape (``object.shape``), None without an object.
        radius: The object's radius [m] (cylinder, sphere).
        height: The object's height [m] (cylinder).
        size: The object's size [m] (plane: (x, y); box: (x, y, z)).
        depth: Offset past the surface along the approach [m] (default
            :data:`DEFAULT_DEPTH`).
        rings: ``cylinder_side``: number of rings (default: an even spacing).

    Raises:
        ConfigError: An object of another shape, or none; a depth past the
            object's centre.
    """
    depth = depth if depth is not None else DEFAULT_DEPTH[source]
    if source in ("cylinder_side", "sphere") and radius:
        _check_depth(depth, radius, "radius")
    if source == "box" and size:
        _check_depth(depth, 0.5 * min(size), "half of the box's smallest side")
    want = GENERATORS.get(source)
    if want is None:  # pragma: no cover - the config allows only the generators
        raise ConfigError(f"candidates.source {source!r} is not a generator")
    if shape != want:
        got = "no 'object' section" if shape is None else f"object.shape {shape!r}"
        raise ConfigError(f"candidates.source {source!r} needs object.shape {want!r}, got {got}")
    if source == "plane":
        assert size is not None
        return poses_plane(count, (size[0], size[1]), rng, depth=depth)
    if source == "cylinder_side":
        assert radius is not None and height is not None
        return poses_cylinder_side(count, radius, height, rings=rings, depth=depth)
    if source == "box":
        assert size is not None
        sx, sy, sz = size
        return poses_box(count, (sx, sy, sz), rng, depth=depth)
    assert radius is not None
    return poses_sphere(count, radius, depth=depth)
