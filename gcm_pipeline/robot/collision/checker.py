"""Collision checking of robot configurations against itself, the world and the object.

The robot's collision meshes come from the same example-robot-data files as its
kinematic model (:meth:`Robot.build_geometry`), reduced with the same locked
joints (the Panda's fingers are locked *open*, as given in the robot spec). The
world is a list of :class:`WorldShape` objects, coal geometries placed in the
robot's base frame (:func:`gcm_pipeline.stages.collision.world_shapes` builds
them from a config): the support table and obstacles (kind ``environment``) and
the object being grasped (kind ``object``). This module takes plain shapes and
arrays; it knows no config.

Pairs that are checked, by kind (the ``reason`` a colliding configuration gets):

``collision_environment``
    every robot link vs every environment shape, except a support shape (the
    table) vs the robot's base links standing on it: links attached to the
    universe or to the first joint that touch it in the home configuration
    (``panda_link0``; ``panda_link1`` is 0.14 m above it and stays checked).
``collision_self``
    all link pairs on different joints, minus the pairs the SRDF disables
    (``pin.removeCollisionPairs``) and adjacent links (parent/child joints).
``collision_object``
    every robot link, the open fingers included, vs the object. The *gripper*
    (the body that carries the grasp frame and every link below it: ``panda_hand``
    and both fingers) may press into the object by ``contact_tolerance`` ``t``
    at the grasp (a finger pad closing on the surface is a grasp, not a collision):

    * a **primitive** object (cylinder, box, sphere, a thin box for a plane) is
      eroded exactly (radius / half-sizes minus ``t``) and checked against the
      gripper: the gripper collides when one of its points lies deeper than
      ``t`` inside the object. A 2 mm plane erodes to nothing, so the gripper
      may touch it;
    * for a **mesh** object each convex collision piece of the gripper is
      eroded by ``t`` instead (:mod:`gcm_pipeline.robot.contact`) and checked
      against the original mesh: the gripper collides when a point of the
      object's surface lies deeper than ``t`` inside one of its pieces. This is
      never more conservative than the geometry, also for walls thinner than
      ``2 t`` (a mug's wall or handle), which an inward offset of the mesh
      cannot represent. A gripper piece that is not convex is checked
      uneroded (a warning says so).

    Arm links (not gripper) are checked against the full object. A closed mesh
    object is a solid: a piece lying wholly inside it, crossing none of its
    triangles, collides too.

When a configuration collides in more than one way, the reason is the first of
environment, self, object.

**Modes** (:meth:`CollisionChecker.check`): ``grasp`` is the above; ``approach``
allows no contact (the gripper against the full object, as the arm); ``retreat``
is the grasp holding the object: the gripper may touch it and the object moves
with the grasp frame (``carried``), checked against the environment
(``collision_environment``) and the arm links (``collision_object``).

**Broad phase**, vectorised over all configurations (NumPy), in three levels.
Every robot collision geometry is covered by a few spheres
(:func:`sphere_cover`: the geometry cut into slabs along its long axis, each
slab's part inside one sphere, so the union of the spheres contains the
geometry) and by one sphere around those; all are placed for all
configurations at once by vectorised forward kinematics
(:class:`~gcm_pipeline.robot.chain.JointFrames`). (1) A pair whose bounding
spheres are apart (from each other, or from the world shape: exact point
distances for boxes, cylinders, spheres and capsules, the local bounding box
of meshes) cannot collide; (2) nor can one whose sphere covers are apart.
(3) A robot polytope against a box (the table, box obstacles) is free when
its convex hull's vertices all lie beyond the plane of one face of the box,
and collides when one of them lies more than 0.1 mm inside the box (the
vertex of one of its triangles; coal, called as Pinocchio calls it, misses
box-box penetrations of a few 1e-5 m, so shallower ones are left to it).
These levels only skip work, they never change an answer (tested pair by pair
against coal on every pair). The compiled kernels (:mod:`gcm_pipeline.robot.kernels`)
run the same three levels one configuration at a time, conservatively: the same
answers. **Narrow phase**: coal, through
``pin.computeCollisionsInParallel`` on a pool holding the pair's two
geometries, only for the (configuration, pair) entries the broad phase left
open. Batches of fewer than ``_FEW`` configurations go to coal's own broad
phase (AABB-tree pools) instead, which costs less to set up, and so do all
batches of a checker with ``threads`` > 1 (those pools run in parallel in C++;
the NumPy broad phase does not). A pair of two
geometries fixed to the world (the base link against an obstacle that
overlaps it) collides in every configuration or in none: it is decided once,
when the checker is built. :meth:`CollisionChecker.clearance` uses the same
spheres as lower bounds and runs coal's exact distance only for pairs that can
still be the nearest.
"""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Any, NamedTuple

import coal
import numpy as np
import pinocchio as pin
from scipy.spatial import ConvexHull, QhullError

from gcm_pipeline.errors import ConfigError, InputError, unknown_choice
from gcm_pipeline.robot import kernels
from gcm_pipeline.robot.chain import JointFrames
from gcm_pipeline.robot.contact import (
    NotConvexError,
    SolidMesh,
    erode_convex,
    interior_point,
    mesh_arrays,
)
from gcm_pipeline.robot.meshes import MeshReadError, read_mesh
from gcm_pipeline.robot.model import Robot

__all__ = [
    "MODES",
    "REASON_ENVIRONMENT",
    "REASON_OBJECT",
    "REASON_SELF",
    "CollisionChecker",
    "SphereCover",
    "WorldShape",
    "as_transform",
    "gripper_links",
    "shape_geometry",
    "sphere_cover",
]

REASON_SELF = "collision_self"
REASON_ENVIRONMENT = "collision_environment"
REASON_OBJECT = "collision_object"

_KINDS = ("environment", "self", "object")
_REASONS = {"environment": REASON_ENVIRONMENT, "self": REASON_SELF, "object": REASON_OBJECT}
#: The reasons as a fixed-width string array (no object arrays to convert).
_REASON_DTYPE = f"<U{max(len(r) for r in _REASONS.values())}"
_OBJECT_SHAPES = ("cylinder", "box", "sphere", "plane", "mesh")
_PLANE_THICKNESS = 0.002  # [m] a 'plane' object is a box this thick, centred on its frame

#: Checking modes: what the gripper may do with the object.
MODES = ("grasp", "approach", "retreat")
_MODE_BIT = {"grasp": 1, "approach": 2, "retreat": 4}
_ALL_MODES = 7

#: A pair is ruled out by the broad phase when its lower bound exceeds this [m]
#: (far above the round-off of the vectorised kinematics, ~1e-12 m).
_BROAD_MARGIN = 1e-7
#: Configurations placed per block by the broad phase (temporaries stay in cache).
_BLOCK = 2048
#: A hull vertex this deep inside a box [m] makes the pair collide without coal.
#: coal, called without contact information as Pinocchio calls it, misses box-box
#: penetrations of up to a few 1e-5 m; shallower ones are left to it.
_INSIDE_DEPTH = 1e-4
#: Fewer configurations than this go to coal's AABB-tree pools instead of the
#: NumPy broad phase (its set-up costs about as much as 100 configurations).
_FEW = 128


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
    on the frame origin; a plane is a ``_PLANE_THICKNESS`` thick box centred on
    the frame's xy plane; a mesh is used as its file defines it (times ``scale``).

    Args:
        shape: ``box``, ``cylinder``, ``sphere``, ``plane`` or ``mesh``.
        dims: An object with ``radius``, ``height``, ``size`` (the config's ``dims``).
        mesh: Mesh file (shape ``mesh``).
        scale: Mesh scale factor.
        erode: Distance [m] by which a primitive shrinks on every side (0: the shape
            itself). Meshes are not eroded (the gripper is, see
            :mod:`gcm_pipeline.robot.contact`): ``erode > 0`` with a mesh is a ValueError.
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
            sizes.append(_PLANE_THICKNESS)
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
                "a mesh is not eroded: the gripper's pieces are (gcm_pipeline.robot.contact)"
            )
        _positive(where, "scale", scale)
        return _load_mesh(mesh, scale, where), centre
    raise ConfigError(f"{where}: " + unknown_choice("shape", shape, _OBJECT_SHAPES))


def erode_primitive(geometry: Any, distance: float) -> Any | None:
    """A coal primitive shrunk by ``distance`` [m] on every side (exact), or None.

    Boxes, spheres and cylinders are eroded exactly; None when nothing is left
    (a part thinner than ``2 * distance``) or for any other geometry (meshes:
    the gripper is eroded instead, see :mod:`gcm_pipeline.robot.contact`).
    """
    if isinstance(geometry, _PRIMITIVES):
        return erode_convex(geometry, distance)
    return None


_PRIMITIVES = (coal.Box, coal.Sphere, coal.Cylinder)
#: Geometries whose points are the convex combinations of their vertices' (hull).
_POLYTOPES = (coal.BVHModelBase, coal.ConvexBase, coal.Box)


# --- sphere covers ------------------------------------------------------------------


class SphereCover(NamedTuple):
    """Spheres whose union contains a geometry (in the frame the points were given in).

    Attributes:
        centres: (K, 3) [m].
        radii: (K,) [m].
    """

    centres: np.ndarray
    radii: np.ndarray


def _box_mesh(lo: np.ndarray, hi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Corners (8, 3) and triangles (12, 3) of an axis-aligned box."""
    corners = np.array(
        [[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])]
    )
    faces = [(0, 1, 3, 2), (4, 6, 7, 5), (0, 4, 5, 1), (2, 3, 7, 6), (0, 2, 6, 4), (1, 5, 7, 3)]
    tris = [(a, b, c) for a, b, c, d in faces] + [(a, c, d) for a, b, c, d in faces]
    return corners, np.array(tris, dtype=int)


def geometry_mesh(geometry: Any) -> tuple[np.ndarray, np.ndarray]:
    """Points (V, 3) and triangles (T, 3) whose triangles cover a coal geometry.

    A mesh gives its own triangles (coal checks a mesh as its surface); a
    convex polytope its hull's; a box its faces; any other shape (sphere,
    cylinder, capsule, ...) the faces of its local bounding box, which contains it.
    """
    if isinstance(geometry, coal.BVHModelBase):
        return mesh_arrays(geometry)
    if isinstance(geometry, coal.ConvexBase):
        pts = np.array(geometry.points(), dtype=float).reshape(-1, 3)
        try:
            return pts, ConvexHull(pts).simplices.astype(int)
        except (QhullError, ValueError):
            pass
    geometry.computeLocalAABB()
    box = geometry.aabb_local
    return _box_mesh(np.asarray(box.min_, dtype=float), np.asarray(box.max_, dtype=float))


def sphere_cover(points: np.ndarray, triangles: np.ndarray, max_spheres: int = 8) -> SphereCover:
    """Spheres whose union contains every triangle (and so their convex hull's parts).

    The geometry is cut into ``K`` slabs of equal length along its principal
    axis (``K`` about twice its length over its width, at most
    ``max_spheres``). The part of the triangles inside a slab lies in the convex
    hull of the vertices in the slab and of the points where triangle edges
    cross the slab's planes; one sphere per slab contains all those points,
    hence that part. The cover of a solid convex piece given by its hull's
    triangles contains the solid too.

    Args:
        points: Vertices (V, 3) [m].
        triangles: (T, 3) int.
        max_spheres: Upper bound of ``K``.

    Returns:
        The :class:`SphereCover`.
    """
    v = np.asarray(points, dtype=float).reshape(-1, 3)
    tris = np.asarray(triangles, dtype=int).reshape(-1, 3)
    mean = v.mean(axis=0)
    _, _, vt = np.linalg.svd(v - mean, full_matrices=False)
    axis = vt[0]
    t = (v - mean) @ axis
    lo, hi = float(t.min()), float(t.max())
    radial = np.linalg.norm((v - mean) - np.outer(t, axis), axis=1).max()
    length = hi - lo
    k = int(np.clip(np.ceil(2.0 * length / max(2.0 * radial, 1e-6)), 1, max_spheres))
    planes = lo + length * np.arange(1, k) / k
    edges = np.unique(
        np.sort(np.concatenate([tris[:, [0, 1]], tris[:, [1, 2]], tris[:, [2, 0]]]), axis=1), axis=0
    )
    ta, tb = t[edges[:, 0]], t[edges[:, 1]]
    extra_pts, extra_t = [], []
    for plane in planes:
        cross = (np.minimum(ta, tb) < plane) & (np.maximum(ta, tb) > plane)
        if np.any(cross):
            e = edges[cross]
            f = ((plane - t[e[:, 0]]) / (t[e[:, 1]] - t[e[:, 0]]))[:, None]
            extra_pts.append(v[e[:, 0]] + f * (v[e[:, 1]] - v[e[:, 0]]))
            extra_t.append(np.full(int(cross.sum()), plane))
    pts = np.concatenate([v, *extra_pts]) if extra_pts else v
    pt_t = np.concatenate([t, *extra_t]) if extra_t else t
    bounds = lo + length * np.arange(k + 1) / k
    centres, radii = [], []
    eps = 1e-12 * max(1.0, length)
    for i in range(k):
        sel = (pt_t >= bounds[i] - eps) & (pt_t <= bounds[i + 1] + eps)
        if not np.any(sel):
            continue
        p = pts[sel]
        c = 0.5 * (p.min(axis=0) + p.max(axis=0))
        centres.append(c)
        radii.append(float(np.linalg.norm(p - c, axis=1).max()) * (1.0 + 1e-9) + 1e-12)
    return SphereCover(np.array(centres), np.array(radii))


# --- lower bounds of point-to-shape distances -------------------------------------------


class _ShapeBound:
    """Lower bound of the distance from points to a placed coal geometry (exact for primitives).

    Boxes, spheres, cylinders and capsules give the exact distance (0 inside);
    any other geometry the distance to its local bounding box.
    """

    def __init__(self, geometry: Any, placement: np.ndarray) -> None:
        self.inv = np.linalg.inv(placement)
        self.kind = "box"
        self.centre = np.zeros(3)
        #: the shape itself (a primitive), not a box around it
        self.exact = isinstance(geometry, (coal.Sphere, coal.Cylinder, coal.Capsule, coal.Box))
        if isinstance(geometry, coal.Sphere):
            self.kind, self.radius = "sphere", float(geometry.radius)
        elif isinstance(geometry, coal.Cylinder):
            self.kind, self.radius = "cylinder", float(geometry.radius)
            self.half = float(geometry.halfLength)
        elif isinstance(geometry, coal.Capsule):
            self.kind, self.radius = "capsule", float(geometry.radius)
            self.half = float(geometry.halfLength)
        elif isinstance(geometry, coal.Box):
            self.halfs = np.asarray(geometry.halfSide, dtype=float)
        else:
            geometry.computeLocalAABB()
            box = geometry.aabb_local
            lo, hi = np.asarray(box.min_, dtype=float), np.asarray(box.max_, dtype=float)
            self.centre = 0.5 * (lo + hi)
            self.halfs = 0.5 * (hi - lo)

    def lower(self, points: np.ndarray) -> np.ndarray:
        """Distances (...,) [m] (>= 0) from points (..., 3) in the base frame."""
        pts = np.asarray(points, dtype=float)
        return self.lower_xyz(pts.reshape(-1, 3).T).reshape(pts.shape[:-1])

    def lower_xyz(self, xyz: np.ndarray) -> np.ndarray:
        """:meth:`lower` of points given by their coordinates (3, ...) (component first)."""
        # each coordinate a contiguous row; einsum, not matmul: OpenBLAS takes ten
        # times longer on a (3, 3) @ (3, K) product
        loc = np.einsum("ij,jk->ik", self.inv[:3, :3], xyz.reshape(3, -1))
        # in place from here on (the same arithmetic; fewer temporaries of K floats)
        loc += self.inv[:3, 3:4]
        x, y, z = loc
        shape = xyz.shape[1:]
        if self.kind == "sphere":
            out = x * x
            out += y * y
            out += z * z
            np.sqrt(out, out=out)
            out -= self.radius
        elif self.kind == "cylinder":
            radial = x * x
            radial += y * y
            np.sqrt(radial, out=radial)
            radial -= self.radius
            axial = np.abs(z, out=z)
            axial -= self.half
            np.maximum(radial, 0.0, out=radial)
            np.maximum(axial, 0.0, out=axial)
            radial *= radial
            axial *= axial
            radial += axial
            return np.sqrt(radial, out=radial).reshape(shape)
        elif self.kind == "capsule":
            along = z - np.clip(z, -self.half, self.half)
            out = x * x
            out += y * y
            out += along * along
            np.sqrt(out, out=out)
            out -= self.radius
        else:
            loc -= self.centre[:, None]
            np.abs(loc, out=loc)
            loc -= self.halfs[:, None]
            np.maximum(loc, 0.0, out=loc)
            loc *= loc
            out = x + y
            out += z
            return np.sqrt(out, out=out).reshape(shape)
        return np.maximum(out, 0.0, out=out).reshape(shape)

    def packed(self) -> np.ndarray:
        """The bound as a row (21,) of the compiled broad phase.

        The inverse placement's first three rows (12), the kind's index in
        :data:`~gcm_pipeline.robot.kernels.SHAPE_KINDS`, the radius, the half
        length, the box's centre (3) and half sizes (3) (0 where they do not apply).
        """
        row = np.zeros(21)
        row[:12] = self.inv[:3].reshape(-1)
        row[12] = kernels.SHAPE_KINDS.index(self.kind)
        if self.kind == "box":
            row[15:18] = self.centre
            row[18:21] = self.halfs
        else:
            row[13] = self.radius
            row[14] = getattr(self, "half", 0.0)
        return row

    def nearest(self, p: np.ndarray) -> np.ndarray:
        """Nearest points (..., 3) of the shape to points ``p`` (..., 3) given in its frame.

        Exact for the primitives (a point inside is its own nearest point).
        """
        if self.kind == "sphere":
            norm = np.sqrt(_sq(p))[..., None]
            return np.where(norm > self.radius, p * (self.radius / np.maximum(norm, 1e-300)), p)
        if self.kind == "cylinder":
            radial = np.sqrt(p[..., 0] ** 2 + p[..., 1] ** 2)[..., None]
            scale = np.minimum(1.0, self.radius / np.maximum(radial, 1e-300))
            out = p * scale
            out[..., 2] = np.clip(p[..., 2], -self.half, self.half)
            return out
        if self.kind == "capsule":
            axis = np.zeros_like(p)
            axis[..., 2] = np.clip(p[..., 2], -self.half, self.half)
            rel = p - axis
            norm = np.sqrt(_sq(rel))[..., None]
            return axis + np.where(
                norm > self.radius, rel * (self.radius / np.maximum(norm, 1e-300)), rel
            )
        return self.centre + np.clip(p - self.centre, -self.halfs, self.halfs)

    def support(self, n: np.ndarray) -> np.ndarray:
        """Support function ``max_{x in shape} n . x`` (...,) of directions ``n`` (..., 3).

        In the shape's frame; exact for the primitives.
        """
        if self.kind == "sphere":
            return self.radius * np.sqrt(_sq(n))
        if self.kind == "cylinder":
            return self.radius * np.sqrt(n[..., 0] ** 2 + n[..., 1] ** 2) + self.half * np.abs(
                n[..., 2]
            )
        if self.kind == "capsule":
            return self.radius * np.sqrt(_sq(n)) + self.half * np.abs(n[..., 2])
        return _row_matmul(n, self.centre) + _row_matmul(np.abs(n), self.halfs)


def _sq(v: np.ndarray) -> np.ndarray:
    """Squared norms (...,) of vectors (..., 3) (faster than ``norm`` along a short axis)."""
    return np.einsum("...i,...i->...", v, v)


# --- the checker -----------------------------------------------------------------------


class _Pair(NamedTuple):
    """One checked pair: geometry indices in the checker's model, and what bounds it."""

    kind: str
    a: int  # robot-side geometry (a link, or an eroded gripper piece)
    b: int  # world geometry, or the other link for self pairs
    owner: int  # robot geometry whose spheres bound ``a``
    other: int  # robot geometry whose spheres bound ``b`` (self pairs), else -1
    modes: int  # bit set of the modes the pair is checked in


class _Screen(NamedTuple):
    """The broad phase of one mode's pairs (columns ``k`` index ``pairs``)."""

    pairs: np.ndarray  # (P,) indices of the checker's pairs
    kind: np.ndarray  # (P,) their kinds
    geom_a: np.ndarray  # (P,) robot geometry whose spheres bound side a
    geom_b: np.ndarray  # (P,) the other robot geometry (self pairs), else -1
    world: np.ndarray  # (P,) world geometry (world pairs), else -1
    # the sphere tests of column k: entries first_test[k]:first_test[k] + n_tests[k]
    # of sphere_a / sphere_b (-1 against the world shape) / bound (reach^2 of two
    # spheres; the radius against a world shape)
    first_test: np.ndarray
    n_tests: np.ndarray
    sphere_a: np.ndarray
    sphere_b: np.ndarray
    bound: np.ndarray
    # robot polytope vs box, by column: (joint, hull vertices (3, V), inverse placement, halfs)
    boxes: dict[int, tuple[int, np.ndarray, np.ndarray, np.ndarray]]


class CollisionChecker:
    """Batched collision checks and clearance of robot configurations (see the module doc).

    Args:
        robot: The robot (its reduced model and collision geometry).
        world: The world shapes in the robot's base frame (at most one of kind
            ``object``).
        contact_tolerance: How deep the gripper may press into the object at
            the grasp [m], >= 0.
        self_collision: Check the robot against itself.
        threads: Threads of ``pin.computeCollisionsInParallel``; with more than one,
            every batch goes to coal's AABB-tree pools (parallel in C++).

    Raises:
        ConfigError: A negative contact tolerance or more than one object.

    Attributes:
        robot: The robot.
        world: The world shapes.
        geom_model: ``pin.GeometryModel`` with the robot links, the eroded
            gripper pieces (mesh object), the world shapes and *every* pair of
            the ``grasp`` mode active; usable with ``pin.computeCollisions``.
        pair_kind: Kind of each pair of ``geom_model.collisionPairs`` (P,) str.
        n_robot_geoms: Number of robot geometries (the first ones of ``geom_model``).
        gripper_geoms: Indices of the gripper geometries.
        link_names: Link of each robot geometry.
        table_exempt: Base links not checked against the support shape.
        contact_tolerance: [m].
        static_collisions: ``(robot link, world shape)`` pairs fixed to the
            world that collide (an obstacle overlapping the base link): every
            configuration collides.
    """

    def __init__(
        self,
        robot: Robot,
        world: Any = (),
        *,
        contact_tolerance: float = 0.005,
        self_collision: bool = True,
        threads: int = 1,
    ) -> None:
        self.robot = robot
        self.world = tuple(world)
        self.threads = max(1, int(threads))
        self.self_collision = bool(self_collision)
        tol = float(contact_tolerance)
        if not math.isfinite(tol) or tol < 0:
            raise ConfigError(f"environment.contact_tolerance must be >= 0 [m], got {tol!r}")
        self.contact_tolerance = tol
        objects = [s for s in self.world if s.kind == "object"]
        if len(objects) > 1:
            raise ConfigError(f"at most one object shape, got {[s.name for s in objects]}")
        for s in self.world:
            if s.kind not in ("environment", "object"):
                raise ConfigError(
                    f"world shape {s.name!r}: "
                    + unknown_choice("kind", s.kind, ("environment", "object"))
                )
        self.object = objects[0] if objects else None

        model = robot.model
        gm = _robot_geometry(robot)
        self.n_robot_geoms = n_rob = int(gm.ngeoms)
        robot_ids = list(range(n_rob))
        link_of = [model.frames[g.parentFrame].name for g in gm.geometryObjects]
        joint_of = [int(g.parentJoint) for g in gm.geometryObjects]
        self.link_names = tuple(link_of)
        self.gripper_geoms = tuple(i for i in robot_ids if link_of[i] in gripper_links(robot))
        gripper = set(self.gripper_geoms)

        # world geometries (after the robot's and the eroded gripper pieces)
        obj = self.object
        mesh_object = obj is not None and not isinstance(obj.geometry, _PRIMITIVES)
        eroded = _add_eroded_gripper(gm, self.gripper_geoms, tol) if mesh_object else {}
        world_ids: dict[str, int] = {}
        for shape in self.world:
            go = pin.GeometryObject(shape.name, 0, 0, _se3(shape.placement), shape.geometry)
            world_ids[shape.name] = int(gm.addGeometryObject(go))
        contact_id = None
        if obj is not None and not mesh_object:
            shrunk = erode_primitive(obj.geometry, tol) if tol > 0 else obj.geometry
            if shrunk is not None:
                go = pin.GeometryObject("object_contact", 0, 0, _se3(obj.placement), shrunk)
                contact_id = int(gm.addGeometryObject(go))

        # --- pairs --------------------------------------------------------------------
        pairs: list[_Pair] = []
        if self.self_collision:
            for a, b in _self_pairs(robot, joint_of):
                pairs.append(_Pair("self", a, b, a, b, _ALL_MODES))
        exempt: set[int] = set()
        for shape in self.world:
            if shape.kind == "environment" and shape.support:
                exempt |= _support_exempt(robot, gm, world_ids[shape.name], joint_of)
        self.table_exempt = tuple(sorted({link_of[i] for i in exempt}))
        for shape in self.world:
            if shape.kind != "environment":
                continue
            w = world_ids[shape.name]
            for i in robot_ids:
                if shape.support and i in exempt:
                    continue
                pairs.append(_Pair("environment", i, w, i, -1, _ALL_MODES))
        if obj is not None:
            w = world_ids[obj.name]
            grasp, approach = _MODE_BIT["grasp"], _MODE_BIT["approach"]
            for i in robot_ids:
                if i not in gripper:
                    # arm links vs the object where it stands (not while carried)
                    pairs.append(_Pair("object", i, w, i, -1, grasp | approach))
                    continue
                pairs.append(_Pair("object", i, w, i, -1, approach))  # no contact on the way in
                if mesh_object:
                    piece = eroded[i]
                    if piece is not None:
                        pairs.append(_Pair("object", piece, w, i, -1, grasp))
                elif contact_id is not None:
                    pairs.append(_Pair("object", i, contact_id, i, -1, grasp))
        self._pairs = pairs
        self._gm = gm

        self._pair_modes = np.array([p.modes for p in pairs], dtype=int)
        self._pair_kind = np.array([p.kind for p in pairs], dtype=object)

        # sphere covers (broad phase, clearance bounds, the carried object)
        self._frames = JointFrames(model)
        # the robot's own sphere covers and hull vertices: computed once per robot
        cover = robot.cache.get("collision_cover")
        if cover is None:
            cover = robot.cache["collision_cover"] = _covers(
                gm, robot_ids, self._frames, max_spheres=8
            )
        self._cover = cover
        #: _place's grouping of points by joint, by the joints' bytes
        self._groups: dict[bytes, list[tuple[int, np.ndarray]]] = {}
        #: the arguments of the compiled broad phase, by screen (see _compiled_screen)
        self._compiled_args: dict[int, tuple[_Screen, tuple[Any, ...], dict[int, Any]]] = {}
        self._bounds = {
            w: _ShapeBound(
                gm.geometryObjects[w].geometry, gm.geometryObjects[w].placement.homogeneous
            )
            for w in {p.b for p in pairs if p.kind != "self"}
        }
        self._hulls: dict[int, tuple[int, np.ndarray]] = robot.cache.setdefault(
            "collision_hulls", {}
        )
        # the narrow phase: one pool per pair (its two geometries only)
        self._pair_pool = [_pair_pool(model, gm, p, self.threads) for p in pairs]
        # pairs of two geometries fixed to the world (the base link against an obstacle)
        # collide in every configuration or in none: decided once, here
        fixed = [
            k
            for k, p in enumerate(pairs)
            if gm.geometryObjects[p.a].parentJoint == 0 and gm.geometryObjects[p.b].parentJoint == 0
        ]
        static_hit = {
            k
            for k in fixed
            if self._run(self._pair_pool[k], np.asarray(robot.home, dtype=float)[None])[0]
        }
        moving = [k for k in range(len(pairs)) if k not in fixed]
        self.static_collisions = tuple(
            (link_of[pairs[k].owner], gm.geometryObjects[pairs[k].b].name)
            for k in sorted(static_hit)
        )
        # a few configurations: coal's own broad phase (an AABB tree) per mode, and per
        # mode and kind for the reason of those that collide (no NumPy set-up cost)
        self._mode_pool: dict[int, Any] = {}
        self._kind_pool: dict[tuple[int, str], Any] = {}
        self._screens: dict[int, _Screen] = {}
        self._static_reason: dict[int, str] = {}
        for bit in _MODE_BIT.values():
            cols = [k for k in moving if pairs[k].modes & bit]
            active = [pairs[k] for k in cols]
            if active:
                self._mode_pool[bit] = _tree_pool(model, gm, active, self.threads)
            for kind in _KINDS:
                some = [p for p in active if p.kind == kind]
                if some:
                    self._kind_pool[bit, kind] = _tree_pool(model, gm, some, self.threads)
            self._screens[bit] = self._screen(cols)
            hit_kinds = {pairs[k].kind for k in static_hit if pairs[k].modes & bit}
            first = next((kind for kind in _KINDS if kind in hit_kinds), None)
            if first is not None:
                self._static_reason[bit] = _REASONS[first]

        # the mesh object as a solid: pieces wholly inside it
        self._init_solid(gm, world_ids)

        # every grasp-mode pair in one model (for colliding_pairs and independent checks)
        full = gm.copy()
        full.removeAllCollisionPairs()
        kinds: list[str] = []
        for kind in _KINDS:
            for p in pairs:
                if p.kind == kind and p.modes & _MODE_BIT["grasp"]:
                    full.addCollisionPair(pin.CollisionPair(p.a, p.b))
                    kinds.append(kind)
        self.geom_model = full
        self.pair_kind = np.array(kinds, dtype=object)
        self._data = model.createData()
        self._full_data = pin.GeometryData(full)

        # clearance: robot vs environment, arm links (not gripper) vs the full object;
        # base links (universe, first joint) vs a support are left out: their distance
        # to it does not depend on the configuration and would mask the arm's
        base_links = {i for i in robot_ids if joint_of[i] in (0, 1)}
        supports = {world_ids[s.name] for s in self.world if s.support}
        dist = [
            p
            for p in pairs
            if (p.kind == "environment" and not (p.a in base_links and p.b in supports))
            or (p.kind == "object" and p.a not in gripper and p.modes & _MODE_BIT["grasp"])
        ]
        self._dist_model: Any = None
        if dist:
            dm = gm.copy()
            dm.removeAllCollisionPairs()
            for p in dist:
                dm.addCollisionPair(pin.CollisionPair(p.a, p.b))
            self._dist_model = dm
            self._dist_data = _without_cached_guess(pin.GeometryData(dm))
            self._dist_owner = np.array([p.owner for p in dist], dtype=int)
            self._dist_world = np.array([p.b for p in dist], dtype=int)
            # a robot polytope against a primitive: its hull vertices give distances
            # (exact to boxes in a face's region, else within a known margin)
            self._box_pairs: dict[int, tuple[np.ndarray, np.ndarray, int]] = {}
            self._vertex_pairs: dict[int, tuple[int, int]] = {}
            for col, p in enumerate(dist):
                world = gm.geometryObjects[p.b]
                robot_geom = gm.geometryObjects[p.a].geometry
                if not isinstance(robot_geom, _POLYTOPES) or p.a != p.owner:
                    continue
                if self._bounds_for(p.b).exact:
                    self._vertex_pairs[col] = (p.a, p.b)
                if not isinstance(world.geometry, coal.Box):
                    continue
                self._hull(p.a)
                self._box_pairs[col] = (
                    np.linalg.inv(world.placement.homogeneous),
                    np.asarray(world.geometry.halfSide, dtype=float),
                    p.a,
                )

        # the carried object (retreat): its cover in its own frame and its pairs
        self._carried = None
        if obj is not None:
            pts, tris = geometry_mesh(obj.geometry)
            self._carried = _CarriedObject(
                obj,
                sphere_cover(pts, tris, max_spheres=8),
                [world_ids[s.name] for s in self.world if s.kind == "environment"],
                [i for i in robot_ids if i not in gripper],
            )

    # --- construction helpers ---------------------------------------------------------

    def _hull(self, g: int) -> tuple[int, np.ndarray]:
        """Hull vertices of robot geometry ``g < n_robot_geoms``: ``(joint, (V, 3))`` (cached)."""
        if g not in self._hulls:
            self._hulls[g] = _hull_vertices(self._gm.geometryObjects[g], self._frames)
        return self._hulls[g]

    def _screen(self, cols: list[int]) -> _Screen:
        """The broad phase of the pairs ``cols`` (indices of ``self._pairs``) of one mode."""
        cov, gm = self._cover, self._gm
        sa, sb, bound = [], [], []
        boxes = {}
        for k, c in enumerate(cols):
            p = self._pairs[c]
            own = np.arange(cov.start[p.owner], cov.start[p.owner + 1])
            if p.kind == "self":
                oth = np.arange(cov.start[p.other], cov.start[p.other + 1])
                ia, ib = np.repeat(own, oth.size), np.tile(oth, own.size)
                sa.append(ia)
                sb.append(ib)
                bound.append((cov.radius[ia] + cov.radius[ib] + _BROAD_MARGIN) ** 2)
                continue
            sa.append(own)
            sb.append(np.full(own.size, -1))
            bound.append(cov.radius[own])
            shape = gm.geometryObjects[p.b]
            if (
                p.a == p.owner
                and isinstance(shape.geometry, coal.Box)
                and isinstance(gm.geometryObjects[p.a].geometry, _POLYTOPES)
            ):
                inv = np.linalg.inv(shape.placement.homogeneous)
                joint, verts = self._hull(p.a)
                boxes[k] = (joint, verts.T.copy(), inv, np.asarray(shape.geometry.halfSide))
        pairs = [self._pairs[c] for c in cols]
        count = np.array([x.size for x in sa], dtype=int)

        def cat(parts: list[np.ndarray], dtype: Any) -> np.ndarray:
            return np.concatenate(parts).astype(dtype) if parts else np.zeros(0, dtype=dtype)

        return _Screen(
            np.array(cols, dtype=int),
            np.array([p.kind for p in pairs], dtype=object),
            np.array([p.owner for p in pairs], dtype=int),
            np.array([p.other if p.kind == "self" else -1 for p in pairs], dtype=int),
            np.array([-1 if p.kind == "self" else p.b for p in pairs], dtype=int),
            np.cumsum(count) - count,
            count,
            cat(sa, int),
            cat(sb, int),
            cat(bound, float),
            boxes,
        )

    def _init_solid(self, gm: Any, world_ids: dict[str, int]) -> None:
        """Inside test of a mesh object for the robot pieces of the object pairs.

        coal checks a mesh object as its triangles; a robot piece (an arm link,
        a gripper piece) that lies wholly inside the closed mesh crosses none of
        them. Such a piece is found by testing one of its points
        (:func:`~gcm_pipeline.robot.contact.interior_point`) against the solid
        (:class:`~gcm_pipeline.robot.contact.SolidMesh`).
        """
        self._solid: SolidMesh | None = None
        obj = self.object
        if obj is None or not isinstance(obj.geometry, coal.BVHModelBase):
            return
        w = world_ids[obj.name]
        rows = [k for k, p in enumerate(self._pairs) if p.kind == "object" and p.b == w]
        if not rows:
            return
        self._solid = SolidMesh(*mesh_arrays(obj.geometry))
        self._solid_from_base = np.linalg.inv(obj.placement)
        self._solid_pair = np.array(rows, dtype=int)
        pieces = [gm.geometryObjects[self._pairs[k].a] for k in rows]
        self._solid_names = tuple(go.name for go in pieces)
        self._solid_joint = np.array([int(go.parentJoint) for go in pieces], dtype=int)
        self._solid_local = np.array(
            [
                self._frames.local(
                    int(go.parentJoint), np.eye(3), go.placement.act(interior_point(go.geometry))
                )[1]
                for go in pieces
            ]
        )

    # --- placing points -------------------------------------------------------------------

    def _place(
        self,
        frames: Any,
        joints: np.ndarray,
        local: np.ndarray,
        rows: np.ndarray | None = None,
    ) -> np.ndarray:
        """Points (N, P, 3) [m], base frame, of ``local`` (P, 3) fixed to ``joints`` (P,).

        ``rows``: only these configurations of ``frames`` (M,), giving (M, P, 3).
        """
        tfs = frames.transforms
        n = tfs[0].shape[0] if rows is None else rows.size
        groups = self._groups.get(joints.tobytes())
        if groups is None:
            groups = self._groups[joints.tobytes()] = [
                (j, np.flatnonzero(joints == j)) for j in np.unique(joints).tolist()
            ]
        out = np.empty((n, len(joints), 3)) if len(groups) != 1 else None
        for j, cols in groups:
            tf = tfs[j] if rows is None else tfs[j][rows]
            # (N * 3, 4) @ (4, P_j), the points in homogeneous coordinates: one BLAS call
            # per joint, rotation and translation at once
            homo = np.ones((4, cols.size))
            homo[:3] = local[cols].T
            placed = (tf.reshape(-1, 4) @ homo).reshape(n, 3, cols.size).transpose(0, 2, 1)
            if out is None:  # every point on one joint
                return np.ascontiguousarray(placed)
            out[:, cols] = placed
        assert out is not None
        return out

    def _run(self, pool: Any, q: np.ndarray) -> np.ndarray:
        """Whether each configuration (M, nq) collides for the pairs of ``pool``, (M,) bool."""
        if len(q) == 0:
            return np.zeros(0, dtype=bool)
        res = pin.computeCollisionsInParallel(
            self.threads, pool, np.asfortranarray(q.T), True, False
        )
        return np.asarray(res, dtype=bool).reshape(len(q))

    # --- queries --------------------------------------------------------------------------

    def check(self, q: Any, mode: str = "grasp", carried: Any = None) -> np.ndarray:
        """Collision reason of each configuration.

        Args:
            q: Configurations (N, nq) or (nq,) [rad]. Non-finite rows are skipped
                (reason ``''``); the caller marks them unreachable anyway.
            mode: ``grasp`` (the gripper may touch the object by the contact
                tolerance), ``approach`` (no contact) or ``retreat`` (the gripper
                holds the object, carried along, see ``carried``).
            carried: ``retreat`` only: the pose of the object in the grasp frame,
                (N, 4, 4) or (4, 4) (``inv(T_grasp) @ T_object`` at the grasp);
                None: the object is not checked.

        Returns:
            (N,) str: ``''`` (free), ``'collision_environment'``,
            ``'collision_self'`` or ``'collision_object'`` (first that applies,
            in this order).

        Raises:
            InputError: Unknown mode or ``carried`` of the wrong shape.
        """
        if mode not in _MODE_BIT:
            raise InputError(unknown_choice("collision mode", mode, MODES))
        qs = self.robot.as_configurations(q)
        n = len(qs)
        held = None
        if carried is not None and mode == "retreat" and self._carried is not None:
            held = np.broadcast_to(np.asarray(carried, dtype=float), (n, 4, 4))
        reason = np.full(n, "", dtype=_REASON_DTYPE)
        rows = np.flatnonzero(np.all(np.isfinite(qs), axis=1))
        for a in range(0, rows.size, _BLOCK):
            block = rows[a : a + _BLOCK]
            reason[block] = self._check_block(
                qs[block], _MODE_BIT[mode], None if held is None else held[block]
            )
        return reason

    def _check_block(self, q: np.ndarray, bit: int, held: np.ndarray | None) -> np.ndarray:
        n = len(q)
        reason = np.full(n, "", dtype=_REASON_DTYPE)
        all_frames = None
        if n < _FEW or self.threads > 1:
            pool = self._mode_pool.get(bit)
            todo = np.flatnonzero(self._run(pool, q)) if pool is not None else np.zeros(0, int)
            for kind in _KINDS:
                kind_pool = self._kind_pool.get((bit, kind))
                if kind_pool is None or todo.size == 0:
                    continue
                hit = self._run(kind_pool, q[todo])
                reason[todo[hit]] = _REASONS[kind]
                todo = todo[~hit]
        else:
            screen = self._screens[bit]
            all_frames = self._frames.compute(q)
            hit = self._pair_hits(q, all_frames, screen)
            for kind in _KINDS:
                some = np.flatnonzero(hit[:, screen.kind == kind].any(axis=1) & (reason == ""))
                reason[some] = _REASONS[kind]
        static = self._static_reason.get(bit)
        if static is not None:
            # a static pair collides in every configuration: its kind unless an earlier one
            order = [_REASONS[k] for k in _KINDS]
            later = np.isin(reason, ["", *order[order.index(static) + 1 :]])
            reason[later] = static
        free = np.flatnonzero(reason == "")
        if free.size and (self._solid is not None or held is not None):
            if all_frames is None:
                frames = self._frames.compute(q[free])
            else:
                frames = all_frames.take(free)
            if self._solid is not None:
                inside = self._inside_object(frames, np.arange(free.size), bit)
                reason[free[inside]] = REASON_OBJECT
            if held is not None:
                still = np.flatnonzero(reason[free] == "")
                sub = frames.take(still)
                grasp_pose = self.robot.fk(q[free[still]])
                for kind in ("environment", "object"):
                    hit = self._carried_collides(kind, sub, grasp_pose, held[free[still]])
                    reason[free[still[hit]]] = _REASONS[kind]
                    still, grasp_pose = still[~hit], grasp_pose[~hit]
                    sub = sub.take(np.flatnonzero(~hit))
                    if still.size == 0:
                        break
        return reason

    def _pair_hits(self, q: np.ndarray, frames: Any, screen: _Screen) -> np.ndarray:
        """Which pairs of ``screen`` collide in each configuration, (N, P) bool.

        Broad phase, in three levels: a pair whose geometries' bounding spheres
        are apart (from each other, or from the world shape) is free; so is
        one whose sphere covers are. A robot polytope against a box is free if
        its hull vertices all lie beyond one face's plane, and collides if one
        of them lies ``_INSIDE_DEPTH`` inside the box (a vertex of one of its
        triangles, or of the solid). coal's narrow phase decides the rest, pair
        by pair, only on the configurations left.
        """
        if screen.pairs.size == 0:  # e.g. no table, no object, no self-collision
            return np.zeros((len(q), 0), dtype=bool)
        compiled = kernels.get()
        if compiled is not None:
            return self._pair_hits_compiled(compiled, q, frames, screen)
        cov, rots, poss = self._cover, frames[0], frames[1]
        # 1. one bounding sphere per robot geometry
        ball = self._place(frames, cov.ball_joint, cov.ball_centre)  # (N, G, 3)
        # coordinates first, (3, G, N): gathers of whole rows, contiguous arithmetic
        xyz = np.ascontiguousarray(ball.transpose(2, 1, 0))
        open_ = np.zeros((screen.pairs.size, len(q)), dtype=bool)  # (P, N)
        own = screen.geom_b >= 0
        if own.any():
            ga, gb = screen.geom_a[own], screen.geom_b[own]
            # one coordinate at a time: temporaries of (pairs, N), not (3, pairs, N)
            # (large temporaries cost page faults)
            sq = np.zeros((ga.size, len(q)))
            for c in xyz:
                d = c[ga] - c[gb]
                sq += d * d
            reach = cov.ball_radius[ga] + cov.ball_radius[gb]
            open_[own] = sq <= ((reach + _BROAD_MARGIN) ** 2)[:, None]
        for w in np.unique(screen.world[screen.world >= 0]).tolist():
            at = np.flatnonzero(screen.world == w)
            g = screen.geom_a[at]
            lb = self._bounds_for(w).lower_xyz(xyz[:, g]) - cov.ball_radius[g][:, None]
            open_[at] = lb <= _BROAD_MARGIN
        hit = np.zeros((len(q), screen.pairs.size), dtype=bool)
        for k in np.flatnonzero(open_.any(axis=1)).tolist():
            rows = np.flatnonzero(open_[k])
            # 2. the sphere covers
            span = slice(screen.first_test[k], screen.first_test[k] + screen.n_tests[k])
            a, b, bound = screen.sphere_a[span], screen.sphere_b[span], screen.bound[span]
            ca = self._place(frames, cov.joint[a], cov.centre[a], rows)
            if screen.world[k] < 0:
                gap = ca - self._place(frames, cov.joint[b], cov.centre[b], rows)
                near = (_sq(gap) <= bound).any(axis=1)
            else:
                lb = self._bounds_for(int(screen.world[k])).lower(ca) - bound
                near = (lb <= _BROAD_MARGIN).any(axis=1)
            rows = rows[near]
            # 3. hull vertices against a box
            box = screen.boxes.get(k)
            if box is not None and rows.size:
                joint, verts, inv, halfs = box
                lim = halfs[None, :, None]

                # the face nearest the geometry's bounding sphere first: its lowest
                # hull vertex over that face's plane (one coordinate), then all of them
                g = screen.geom_a[k]
                centre = _row_matmul(ball[rows, g], inv[:3, :3].T) + inv[:3, 3]
                axis = np.argmax(np.abs(centre) - halfs, axis=1)
                sign = np.where(centre[np.arange(rows.size), axis] >= 0, 1.0, -1.0)
                frame = (rots[joint][rows], poss[joint][rows], inv)
                height = _height_over_face(frame, verts, halfs, axis, sign)
                rows = rows[height <= _BROAD_MARGIN]
                local = _in_frame((rots[joint], poss[joint], inv), rows, verts)
                inside = np.all(np.abs(local) < lim - _INSIDE_DEPTH, axis=1).any(axis=1)
                hit[rows[inside], k] = True
                rows = rows[~(_beyond_a_face(local, lim) | inside)]
            if rows.size:
                hit[rows, k] = self._run(self._pair_pool[screen.pairs[k]], q[rows])
        return hit

    def _pair_hits_compiled(
        self, compiled: kernels.Kernels, q: np.ndarray, frames: Any, screen: _Screen
    ) -> np.ndarray:
        """:meth:`_pair_hits` by the compiled kernels (see :mod:`~gcm_pipeline.robot.kernels`).

        The same answers: levels 1 and 2 for all pairs in one pass, then level 3
        and coal pair by pair.
        """
        tfs = _stacked(frames.transforms)
        broad, boxes = self._compiled_screen(screen)
        open_ = compiled.broad_phase(tfs, *broad)  # (P, N)
        hit = np.zeros((len(q), screen.pairs.size), dtype=bool)
        for k in np.flatnonzero(open_.any(axis=1)).tolist():
            rows = np.flatnonzero(open_[k])
            box = boxes.get(k)
            if box is not None:
                joint, *limits = box
                status = compiled.hull_vs_box(tfs[joint], rows, *limits)
                hit[rows[status == kernels.COLLIDES], k] = True
                rows = rows[status == kernels.UNDECIDED]
            if rows.size:
                hit[rows, k] = self._run(self._pair_pool[screen.pairs[k]], q[rows])
        return hit

    def _compiled_screen(self, screen: _Screen) -> tuple[tuple[Any, ...], dict[int, Any]]:
        """The compiled broad phase's arguments for ``screen`` (built once per screen).

        Returns the arguments of ``broad_phase`` after the frames, and the
        level-3 arguments ``(joint, vertices, inverse placement, beyond, deep)``
        of each column with a box. Each limit is the NumPy level's plus
        :data:`~gcm_pipeline.robot.kernels.SLACK` (level 3: minus it, for the depth).
        """
        known = self._compiled_args.get(id(screen))
        if known is not None and known[0] is screen:
            return known[1], known[2]
        cov, slack = self._cover, kernels.SLACK
        worlds = sorted({int(w) for w in screen.world.tolist() if w >= 0})
        # explicit dtypes: without a world shape or a pair these lists are empty
        # (and np.array([]) is float64)
        shapes = np.array([self._bounds_for(w).packed() for w in worlds], float).reshape(-1, 21)
        world = np.array(
            [worlds.index(w) if w >= 0 else -1 for w in screen.world.tolist()], np.intp
        )
        own = world < 0
        ra = cov.ball_radius[screen.geom_a]
        rb = cov.ball_radius[np.where(own, screen.geom_b, 0)]
        # self pairs compare squared gaps with squared limits; world pairs distances
        limit1 = np.where(own, (ra + rb + _BROAD_MARGIN + slack) ** 2, ra + _BROAD_MARGIN + slack)
        limit2 = np.where(
            np.repeat(own, screen.n_tests),
            (np.sqrt(screen.bound) + slack) ** 2,
            screen.bound + _BROAD_MARGIN + slack,
        )
        args = [cov.ball_joint, cov.ball_centre, cov.joint, cov.centre, screen.geom_a]
        args += [screen.geom_b, world, limit1, screen.first_test, screen.n_tests]
        args += [screen.sphere_a, screen.sphere_b, limit2, shapes]
        # indices as intp, all C-contiguous (the kernels' signature)
        broad = tuple(
            np.ascontiguousarray(a, np.float64 if a.dtype.kind == "f" else np.intp) for a in args
        )
        boxes = {
            k: (
                joint,
                np.ascontiguousarray(verts, float),
                np.ascontiguousarray(inv, float),
                halfs + (_BROAD_MARGIN + slack),
                halfs - (_INSIDE_DEPTH + slack),
            )
            for k, (joint, verts, inv, halfs) in screen.boxes.items()
        }
        self._compiled_args[id(screen)] = (screen, broad, boxes)
        return broad, boxes

    def _inside_object(self, frames: Any, rows: np.ndarray, bit: int) -> np.ndarray:
        """Whether an active robot piece lies inside the mesh object, (M,) bool."""
        out = np.zeros(rows.size, dtype=bool)
        use = np.flatnonzero(self._pair_modes[self._solid_pair] & bit)
        if self._solid is None or rows.size == 0 or use.size == 0:
            return out
        sub = frames.take(rows)
        pts = self._place(sub, self._solid_joint[use], self._solid_local[use])
        m = self._solid_from_base
        local = pts @ m[:3, :3].T + m[:3, 3]
        inside = self._solid.contains(local.reshape(-1, 3)).reshape(pts.shape[:2])
        return np.asarray(inside.any(axis=1), dtype=bool)

    def _carried_collides(
        self, kind: str, frames: Any, grasp_pose: np.ndarray, held: np.ndarray
    ) -> np.ndarray:
        """The carried object against the environment or the arm links, (M,) bool.

        Sphere covers rule out most pairs; coal decides the others.
        """
        m = grasp_pose.shape[0]
        out = np.zeros(m, dtype=bool)
        car = self._carried
        if car is None or m == 0:
            return out
        pose = grasp_pose @ held  # the object in the base frame
        centres = car.cover.centres @ np.swapaxes(pose[:, :3, :3], 1, 2) + pose[:, None, :3, 3]
        gm = self._gm
        req = coal.CollisionRequest()
        res = coal.CollisionResult()
        obj_geom = car.shape.geometry
        if kind == "environment":
            for w in car.environment:
                lb = (self._bounds_for(w).lower(centres) - car.cover.radii).min(axis=1)
                go = gm.geometryObjects[w]
                tf_w = _tf(go.placement.homogeneous)
                for i in np.flatnonzero((lb <= _BROAD_MARGIN) & ~out).tolist():
                    res.clear()
                    if coal.collide(obj_geom, _tf(pose[i]), go.geometry, tf_w, req, res):
                        out[i] = True
            return out
        cov = self._cover
        cw = self._place(frames, cov.joint, cov.centre)
        for g in car.arm:
            s = np.arange(cov.start[g], cov.start[g + 1])
            gap = np.linalg.norm(cw[:, s, None, :] - centres[:, None, :, :], axis=3)
            lb = (gap - cov.radius[s][:, None] - car.cover.radii[None, :]).min(axis=(1, 2))
            go = gm.geometryObjects[g]
            j = int(go.parentJoint)
            rl, tl = self._frames.local(
                j, np.asarray(go.placement.rotation), np.asarray(go.placement.translation)
            )
            for i in np.flatnonzero((lb <= _BROAD_MARGIN) & ~out).tolist():
                tf = np.eye(4)
                tf[:3, :3] = frames[0][j][i] @ rl
                tf[:3, 3] = frames[1][j][i] + frames[0][j][i] @ tl
                res.clear()
                if coal.collide(go.geometry, _tf(tf), obj_geom, _tf(pose[i]), req, res):
                    out[i] = True
        return out

    def _bounds_for(self, w: int) -> _ShapeBound:
        bound = self._bounds.get(w)
        if bound is None:
            go = self._gm.geometryObjects[w]
            bound = self._bounds[w] = _ShapeBound(go.geometry, go.placement.homogeneous)
        return bound

    def in_collision(self, q: Any, mode: str = "grasp") -> np.ndarray:
        """Whether each configuration collides (any kind), (N,) bool."""
        return self.check(q, mode) != ""

    def colliding_pairs(self, q: Any) -> list[tuple[str, str, str]]:
        """All colliding pairs of one configuration in the ``grasp`` mode (for reports).

        Args:
            q: One configuration (nq,) [rad].

        Returns:
            ``[(geometry_1, geometry_2, kind), ...]``; a robot piece wholly inside a
            mesh object is ``(piece, "object (inside)", "object")``.
        """
        qs = self.robot.as_configurations(q)[0]
        gm, gd = self.geom_model, self._full_data
        pin.computeCollisions(self.robot.model, self._data, gm, gd, qs, False)
        out = []
        if self._solid is not None:
            frames = self._frames.compute(qs[None])
            inside = self._inside_pieces(frames)
            out += [
                (self._solid_names[k], "object (inside)", "object") for k in np.flatnonzero(inside)
            ]
        for k, cp in enumerate(gm.collisionPairs):
            if gd.collisionResults[k].isCollision():
                out.append(
                    (
                        gm.geometryObjects[cp.first].name,
                        gm.geometryObjects[cp.second].name,
                        str(self.pair_kind[k]),
                    )
                )
        return out

    def _inside_pieces(self, frames: Any) -> np.ndarray:
        """Which grasp-mode pieces of one configuration lie inside the mesh object."""
        assert self._solid is not None
        use = self._pair_modes[self._solid_pair] & _MODE_BIT["grasp"] > 0
        pts = self._place(frames, self._solid_joint, self._solid_local)[0]
        m = self._solid_from_base
        return self._solid.contains(pts @ m[:3, :3].T + m[:3, 3]) & use

    def clearance(self, q: Any, precision: float = 1e-3) -> np.ndarray:
        """Minimum distance of the robot to the environment and the object [m].

        Pairs: every robot link vs every environment shape, except the base
        links (fixed to the universe or the first joint) vs a support (the
        table), whose distance to it does not change with the configuration
        (0.14 m for ``panda_link1``), and every *arm* link vs the object. The
        gripper (hand and fingers) vs the object is left out: at a grasp it
        touches the object by design. Penetrating pairs give a distance <= 0
        (a penetration, not necessarily the deepest one).

        Distances are computed in increasing order of the pairs' lower bounds
        (sphere covers), and only while a pair's bound is below the best
        distance found minus ``precision``: exact ones by coal on the meshes,
        or, from the hull vertices (vectorised), the exact distance of a link
        in the region of one face of a box, and the distance of a link's
        nearest vertex from a primitive shape where a separating plane proves
        it within ``precision`` of the pair's. The result is a real distance
        of the robot to the world (between two of their points), at most
        ``precision`` above the minimum (the ranking needs no more).

        Args:
            q: Configurations (N, nq) or (nq,) [rad].
            precision: How far above the true minimum the result may be [m], >= 0.

        Returns:
            (N,) distances [m]; ``inf`` when there is nothing to measure against,
            NaN for non-finite configurations.
        """
        qs = self.robot.as_configurations(q)
        out = np.full(len(qs), np.inf)
        finite = np.all(np.isfinite(qs), axis=1)
        out[~finite] = np.nan
        rows = np.flatnonzero(finite)
        if self._dist_model is None or rows.size == 0:
            return out
        model, data = self.robot.model, self._data
        dm, dd = self._dist_model, self._dist_data
        cov = self._cover
        for a in range(0, rows.size, _BLOCK):
            block = rows[a : a + _BLOCK]
            frames = self._frames.compute(qs[block])
            centres = self._place(frames, cov.joint, cov.centre)
            bound = np.empty((block.size, self._dist_owner.size))
            for w in np.unique(self._dist_world).tolist():
                cols = np.flatnonzero(self._dist_world == w)
                d = self._bounds_for(w).lower(centres) - cov.radius
                per_owner = np.minimum.reduceat(d, cov.start[:-1], axis=1)
                bound[:, cols] = per_owner[:, self._dist_owner[cols]]
            # exact distances to boxes where a link lies in the region of one face, and
            # where they can still be the nearest
            exact = self._face_distances(frames, centres, bound)
            known = np.isfinite(exact)
            bound[known] = exact[known]
            best0 = np.where(known, exact, np.inf).min(axis=1)
            need = ~known & (bound < best0[:, None] - precision)
            # the nearest hull vertex's distance where it is within precision of the pair's
            # (its lower bound stays the pair's bound: what it may still be)
            upper, lower = self._vertex_distances(frames, need & (precision > 0), precision)
            found = np.isfinite(upper)
            exact[found], known[found], bound[found] = upper[found], True, lower[found]
            best0 = np.where(known, exact, np.inf).min(axis=1)
            # coal only for rows with a pair that may still be nearer than best - precision
            need = ~known & (bound < best0[:, None] - precision)
            todo = np.flatnonzero(need.any(axis=1))
            easy = np.setdiff1d(np.arange(block.size), todo)
            out[block[easy]] = best0[easy]
            order = np.argsort(bound[todo], axis=1)
            for k, i in enumerate(todo.tolist()):
                n = int(block[i])
                pin.updateGeometryPlacements(model, data, dm, dd, qs[n])
                best = np.inf
                lb = bound[i]
                for p in order[k].tolist():
                    if lb[p] >= best - precision:
                        break
                    d = exact[i, p] if known[i, p] else pin.computeDistance(dm, dd, p).min_distance
                    if d < best:
                        best = d
                out[n] = best
        return out

    def _vertex_distances(
        self, frames: Any, need: np.ndarray, precision: float
    ) -> tuple[np.ndarray, np.ndarray]:
        """Bounds ``(U, L)`` (N, P) of the clearance pairs' distances, NaN where not known.

        Only the pairs ``need`` (N, P) are looked at.

        For a robot polytope against a primitive shape: ``U``, the distance of
        its nearest hull vertex (a point of the robot) from the shape, bounds
        the pair's distance ``d`` from above. From below, the plane through
        the shape's nearest point normal to that direction separates the shape
        from the hull by ``L = min_v n . v - h(n)`` (``h`` the shape's support
        function), and the robot's geometry lies in its hull: ``L <= d <= U``.
        Both are kept where ``U - L <= precision`` (the vertex is outside the shape).
        """
        out = np.full(need.shape, np.nan)
        below = np.full(need.shape, np.nan)
        rots, poss = frames.rots, frames.poss
        for col in np.flatnonzero(need.any(axis=0)).tolist():
            pair = self._vertex_pairs.get(col)
            if pair is None:
                continue
            rows = np.flatnonzero(need[:, col])
            g, w = pair
            joint, verts = self._hull(g)
            shape = self._bounds_for(w)
            pts = _in_frame((rots[joint], poss[joint], shape.inv), rows, verts.T)
            pts = pts.transpose(0, 2, 1)  # (M, V, 3) in the shape's frame
            gap = pts - shape.nearest(pts)
            dist = np.sqrt(_sq(gap))
            at = np.argmin(dist, axis=1)
            m = np.arange(rows.size)
            upper = dist[m, at]
            outside = upper > 0
            normal = gap[m, at] / np.where(outside, upper, 1.0)[:, None]
            lower = np.einsum("mvi,mi->mv", pts, normal).min(axis=1) - shape.support(normal)
            keep = outside & (upper - lower <= precision)
            out[rows[keep], col] = upper[keep]
            below[rows[keep], col] = lower[keep]
        return out, below

    def _face_distances(self, frames: Any, centres: np.ndarray, bound: np.ndarray) -> np.ndarray:
        """Exact distances (N, P) of the clearance pairs against boxes, NaN where unknown.

        A robot geometry that lies in the region of one face of a box (its
        covering spheres inside the face's rectangle, its hull vertices beyond
        the face's plane) is at the distance of its nearest hull vertex from
        that plane: the distance to the box is linear in that region, so its
        minimum over the geometry is at a hull vertex (what coal computes on
        the mesh, to round-off).

        Pairs whose lower bound ``bound`` (N, P) is no less than an exact
        distance already found for the row are left unknown: their distance
        cannot be below the row's minimum, so the clearance is the same. The
        pairs are visited in a fixed order, the links farthest along the chain first
        (at a grasp they are usually the nearest): a row's result does not depend on
        the other rows of the batch (two pairs can be at the same distance, e.g. the
        two fingers over a table, to round-off).
        """
        n = centres.shape[0]
        out = np.full((n, self._dist_owner.size), np.nan)
        best = np.full(n, np.inf)
        cov = self._cover
        rots, poss = frames.rots, frames.poss
        pairs = self._box_pairs
        cols = sorted(pairs, key=lambda k: (-int(cov.ball_joint[pairs[k][2]]), k))
        for col in cols:
            inv, halfs, g = pairs[col]
            sph = np.arange(cov.start[g], cov.start[g + 1])
            may = np.flatnonzero(bound[:, col] < best)
            if may.size == 0:
                continue
            pts = centres[may][:, sph]
            c = (_row_matmul(pts.reshape(-1, 3), inv[:3, :3].T) + inv[:3, 3]).reshape(pts.shape)
            r = cov.radius[sph]
            joint, verts = self._hulls[g]
            for axis in range(3):
                other = [k for k in range(3) if k != axis]
                lateral = np.all(np.abs(c[:, :, other]) + r[None, :, None] <= halfs[other], axis=2)
                rows = np.flatnonzero(lateral.all(axis=1))
                if rows.size == 0:
                    continue
                # the face on the geometry's side
                sign = np.where(c[rows, 0, axis] >= 0, 1.0, -1.0)
                at = may[rows]
                frame = (rots[joint][at], poss[joint][at], inv)
                height = _height_over_face(frame, verts.T, halfs, np.full(rows.size, axis), sign)
                above = height >= 0
                out[at[above], col] = height[above]
                np.minimum.at(best, at[above], height[above])
        return out

    def with_world(self, world: Any) -> CollisionChecker:
        """The same robot and settings in another world (e.g. the object moved).

        The robot's collision geometry is read once per robot and reused.
        """
        return CollisionChecker(
            self.robot,
            world,
            contact_tolerance=self.contact_tolerance,
            self_collision=self.self_collision,
            threads=self.threads,
        )

    def __repr__(self) -> str:
        counts = {k: int(np.sum(self.pair_kind == k)) for k in _KINDS}
        world = ", ".join(s.name for s in self.world) or "(none)"
        spheres = len(self._cover.radius)
        return (
            f"CollisionChecker(robot={self.robot.name!r}, world=[{world}], pairs={counts}, "
            f"contact_tolerance={self.contact_tolerance}, table_exempt={list(self.table_exempt)}, "
            f"spheres={spheres})"
        )


# --- helpers --------------------------------------------------------------------------


class _Cover(NamedTuple):
    """Sphere covers of all robot geometries, in the joints' rotated frames."""

    centre: np.ndarray  # (S, 3)
    radius: np.ndarray  # (S,)
    joint: np.ndarray  # (S,)
    start: np.ndarray  # (R + 1,) spheres of geometry g: start[g]:start[g + 1]
    ball_centre: np.ndarray  # (R, 3) one sphere per geometry containing its cover
    ball_radius: np.ndarray  # (R,)
    ball_joint: np.ndarray  # (R,)


class _CarriedObject(NamedTuple):
    shape: WorldShape
    cover: SphereCover  # in the object geometry's frame
    environment: list[int]  # world geometries it may hit
    arm: list[int]  # robot geometries it may hit (not the gripper)


def _covers(gm: Any, ids: list[int], frames: JointFrames, max_spheres: int) -> _Cover:
    centres, radii, joints, start = [], [], [], [0]
    balls: list[np.ndarray] = []
    ball_r: list[float] = []
    for i in ids:
        go = gm.geometryObjects[i]
        pts, tris = geometry_mesh(go.geometry)
        cov = sphere_cover(pts, tris, max_spheres)
        j = int(go.parentJoint)
        rot, trans = frames.local(
            j, np.asarray(go.placement.rotation), np.asarray(go.placement.translation)
        )
        centres.append(cov.centres @ rot.T + trans)
        radii.append(cov.radii)
        joints.append(np.full(len(cov.radii), j))
        start.append(start[-1] + len(cov.radii))
        # the sphere around the cover's spheres: centred in their bounding box
        c = centres[-1]
        mid = 0.5 * (c.min(axis=0) + c.max(axis=0))
        balls.append(mid)
        ball_r.append(float((np.linalg.norm(c - mid, axis=1) + cov.radii).max()) * (1 + 1e-12))
    return _Cover(
        np.concatenate(centres),
        np.concatenate(radii),
        np.concatenate(joints),
        np.array(start),
        np.array(balls).reshape(-1, 3),
        np.array(ball_r),
        np.array([int(gm.geometryObjects[i].parentJoint) for i in ids], dtype=int),
    )


def _stacked(tfs: list[np.ndarray]) -> np.ndarray:
    """Joint frames (N, 3, 4) as one (J, N, 3, 4) array: the array they are views of, if any."""
    base = tfs[0].base
    if (
        isinstance(base, np.ndarray)
        and base.shape == (len(tfs), *tfs[0].shape)
        and base.dtype == np.float64
        and base.flags.c_contiguous
        and all(
            t.base is base and t.ctypes.data == base.ctypes.data + j * base.strides[0]
            for j, t in enumerate(tfs)
        )
    ):
        return base
    return np.stack(tfs)


def _row_matmul(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``a @ b`` for a 2-D ``a``, each row's result the same whatever the number of rows.

    NumPy computes a single row with BLAS's vector routine, whose sums can differ
    in the last bit from the matrix routine's; a configuration's answer must not
    depend on the batch it comes in (chunks, workers), so one row is computed as two.
    """
    if a.ndim == 2 and a.shape[0] == 1:
        return (np.concatenate([a, a]) @ b)[:1]
    return a @ b


def _in_frame(frame: tuple[Any, Any, np.ndarray], rows: np.ndarray, points: np.ndarray) -> Any:
    """Points (3, V) fixed to a joint, in a world shape's frame, for configurations ``rows``.

    ``frame`` is the joint's rotations (N, 3, 3) and origins (N, 3) and the
    shape's inverse placement (4, 4). Returns (M, 3, V).
    """
    rots, poss, inv = frame
    m = rows.size
    rot = (inv[:3, :3] @ rots[rows]).reshape(3 * m, 3)
    off = _row_matmul(poss[rows], inv[:3, :3].T) + inv[:3, 3]
    return (rot @ points).reshape(m, 3, points.shape[1]) + off[:, :, None]


def _height_over_face(
    frame: tuple[np.ndarray, np.ndarray, np.ndarray],
    points: np.ndarray,
    halfs: np.ndarray,
    axis: np.ndarray,
    sign: np.ndarray,
) -> np.ndarray:
    """Height (M,) of the lowest of points (3, V) fixed to a joint over one face of a box.

    ``frame`` is the joint's rotations (M, 3, 3) and origins (M, 3) and the
    box's inverse placement (4, 4); the face is the one across ``axis`` (M,)
    on the side ``sign`` (M,, +-1) of the box ``|x| <= halfs``. The height of a
    point v is ``u . (R v + o) + t`` with ``u`` the face's outward normal.
    """
    rots, poss, inv = frame
    normal = sign[:, None] * inv[axis, :3]  # base frame
    w = np.einsum("ni,nij->nj", normal, rots)  # R^T u, the joint's frame
    return (
        _row_matmul(w, points).min(axis=1)
        + np.einsum("ni,ni->n", normal, poss)
        + sign * inv[axis, 3]
        - halfs[axis]
    )


def _beyond_a_face(local: np.ndarray, lim: np.ndarray) -> np.ndarray:
    """Whether all points (M, 3, V) lie beyond one face plane of the box ``|x| <= lim``, (M,)."""
    return (
        np.all(local > lim + _BROAD_MARGIN, axis=2) | np.all(local < -lim - _BROAD_MARGIN, axis=2)
    ).any(axis=1)


def _hull_vertices(go: Any, frames: JointFrames) -> tuple[int, np.ndarray]:
    """A robot geometry's convex hull vertices in its joint's rotated frame: ``(joint, (V, 3))``.

    Only vertices of its triangles count (a mesh may list unused ones): each
    hull vertex is a point of the geometry.
    """
    pts, tris = geometry_mesh(go.geometry)
    pts = pts[np.unique(tris)] if tris.size else pts
    try:
        pts = pts[ConvexHull(pts).vertices]
    except (QhullError, ValueError):
        pass
    j = int(go.parentJoint)
    rot, trans = frames.local(
        j, np.asarray(go.placement.rotation), np.asarray(go.placement.translation)
    )
    return j, pts @ rot.T + trans


def _without_cached_guess(gd: Any) -> Any:
    """Geometry data whose GJK starts from the same guess every time.

    coal reuses the last query's solution as the next initial guess by
    default; an answer then depends on what was asked before (last bits of a
    distance, rarely a borderline contact), so the result of a configuration
    would depend on the chunking and the number of workers.
    """
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DeprecationWarning)
        for req in [*gd.collisionRequests, *gd.distanceRequests]:
            req.enable_cached_gjk_guess = False
            req.gjk_initial_guess = coal.GJKInitialGuess.DefaultGuess
    return gd


def _tree_pool(model: Any, gm: Any, pairs: list[_Pair], threads: int) -> Any:
    """A pool checking ``pairs`` with coal's dynamic AABB tree (broad phase) in C++."""
    km = gm.copy()
    km.removeAllCollisionPairs()
    for p in pairs:
        km.addCollisionPair(pin.CollisionPair(p.a, p.b))
    pool = pin.TreeBroadPhaseManagerPool_DynamicAABBTreeCollisionManager(model, km, threads)
    for i in range(pool.size()):
        _without_cached_guess(pool.getGeometryData(i))
    return pool


def _pair_pool(model: Any, gm: Any, pair: _Pair, threads: int) -> Any:
    """A pool checking one pair with coal's narrow phase (a model of its two geometries)."""
    km = pin.GeometryModel()
    for g in (pair.a, pair.b):
        km.addGeometryObject(gm.geometryObjects[g])
    km.addCollisionPair(pin.CollisionPair(0, 1))
    pool = pin.GeometryPool(model, km, threads)
    for i in range(pool.size()):
        _without_cached_guess(pool.getGeometryData(i))
    return pool


def _tf(m: np.ndarray) -> Any:
    return coal.Transform3s(np.ascontiguousarray(m[:3, :3]), np.ascontiguousarray(m[:3, 3]))


def _se3(m: np.ndarray) -> pin.SE3:
    return pin.SE3(np.ascontiguousarray(m[:3, :3]), np.ascontiguousarray(m[:3, 3]))


def _robot_geometry(robot: Robot) -> Any:
    """A copy of the robot's collision geometry model (read once per robot)."""
    gm = robot.cache.get("collision_geometry")
    if gm is None:
        gm = robot.cache["collision_geometry"] = robot.build_geometry("collision")
    return gm.copy()


def _self_pairs(robot: Robot, joint_of: list[int]) -> list[tuple[int, int]]:
    """Self pairs: all pairs minus the SRDF's disabled ones and same/adjacent links."""
    model = robot.model
    gm = _robot_geometry(robot)
    gm.addAllCollisionPairs()
    if robot.srdf_path is not None:
        pin.removeCollisionPairs(model, gm, str(robot.srdf_path))
    out = []
    for cp in gm.collisionPairs:
        a, b = int(cp.first), int(cp.second)
        ja, jb = joint_of[a], joint_of[b]
        if ja == jb or model.parents[ja] == jb or model.parents[jb] == ja:
            continue  # same rigid body or adjacent links
        out.append((a, b))
    return out


def _support_exempt(robot: Robot, gm: Any, support: int, joint_of: list[int]) -> set[int]:
    """Robot geometries not checked against a support: the base links standing on it.

    Links fixed to the universe or to the first joint that touch the support
    in the home configuration (for the Panda at z = 0: ``panda_link0``).
    """
    model = robot.model
    first = [i for i in range(len(joint_of)) if joint_of[i] in (0, 1)]
    if not first:
        return set()
    probe = gm.copy()
    probe.removeAllCollisionPairs()
    for i in first:
        probe.addCollisionPair(pin.CollisionPair(i, support))
    pd = pin.GeometryData(probe)
    pin.computeCollisions(model, model.createData(), probe, pd, robot.home, False)
    return {
        int(cp.first)
        for k, cp in enumerate(probe.collisionPairs)
        if pd.collisionResults[k].isCollision()
    }


def _add_eroded_gripper(
    gm: Any, gripper_geoms: tuple[int, ...], tol: float
) -> dict[int, int | None]:
    """Add each gripper piece eroded by ``tol`` [m] to ``gm`` (same joint, frame, placement).

    Returns:
        Gripper geometry index -> index of its eroded copy (named ``<name>_contact``),
        or None when the piece erodes to nothing. A piece that cannot be eroded
        (not convex) is used uneroded, with a warning.
    """
    out: dict[int, int | None] = {}
    for i in gripper_geoms:
        go = gm.geometryObjects[i]
        if tol == 0:
            out[i] = i
            continue
        try:
            eroded = erode_convex(go.geometry, tol)
        except NotConvexError as exc:
            warnings.warn(
                f"gripper collision piece {go.name!r}: {exc}; checked against the object "
                "without contact tolerance",
                stacklevel=3,
            )
            out[i] = i
            continue
        if eroded is None:
            out[i] = None
            continue
        piece = pin.GeometryObject(
            f"{go.name}_contact", int(go.parentJoint), int(go.parentFrame), go.placement, eroded
        )
        out[i] = int(gm.addGeometryObject(piece))
    return out


def gripper_links(robot: Robot) -> set[str]:
    """Links of the gripper: the body carrying the grasp frame and all links below it.

    Walks the *full* (unreduced) model's frame tree: the grasp frame's nearest
    BODY ancestor (``panda_hand`` for the Panda) and its descendants
    (``panda_leftfinger``, ``panda_rightfinger``).
    """
    fm = robot.full_model
    fid = robot.full_grasp_frame_id  # by name and type: a joint may share its name
    root = fid
    k = int(fm.frames[fid].parentFrame)
    while k != root and k > 0:
        if fm.frames[k].type == pin.FrameType.BODY:
            root = k
            break
        k = int(fm.frames[k].parentFrame)
    names: set[str] = set()
    for i, f in enumerate(fm.frames):
        j, seen = i, set()
        while j not in seen:
            if j == root:
                if f.type == pin.FrameType.BODY:
                    names.add(f.name)
                break
            seen.add(j)
            if j == 0:
                break
            j = int(fm.frames[j].parentFrame)
    return names
