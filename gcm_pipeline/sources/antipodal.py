r"""Antipodal grasp sampler for parallel-jaw grippers on meshes and primitives.

``candidates: {source: antipodal, count: N, gripper: franka_panda}`` samples
grasps on the config's object (``shape: mesh`` or a primitive) with trimesh:

1. points uniform on the surface (:func:`trimesh.sample.sample_surface`) with
   their face normals :math:`n_1`;
2. a closing direction :math:`d` drawn inside the friction cone around
   :math:`-n_1` (half angle :math:`\arctan \mu`, ``friction`` = :math:`\mu`);
3. a ray cast from just inside the surface along :math:`d` finds the
   opposite contact :math:`p_2` (where the ray leaves the object) and its
   normal :math:`n_2`;
4. the pair is antipodal when :math:`d` lies inside both friction cones
   (:math:`\angle(d, -n_1) \le \arctan\mu` and :math:`\angle(d, n_2) \le
   \arctan\mu`) and the width :math:`|p_2 - p_1|` fits the gripper's opening
   (``max_width``, less 5 mm of clearance);
5. approach directions :math:`z` are spread around the contact axis
   (``approaches`` per pair, evenly spaced from a random phase, all
   perpendicular to :math:`d`); the grasp frame has y = :math:`d` (the
   fingers close along y), z = the approach, and its origin (the fingertip
   midpoint) ``finger_depth / 2`` past the contacts' midpoint along z, so the
   contacts sit in the middle of the finger pads;
6. grasps whose open gripper (points on the fingers and the palm) would be
   inside the object, or whose hand or wrist (points up to 0.25 m behind the
   palm along the approach) would be below the table, are dropped; ``count``
   of the rest are drawn at random.

Per grasp, ``score`` = :math:`\cos` of the larger of the two cone angles (1
for a perfectly antipodal pair) and ``width`` = the contact distance [m] are
kept as per-candidate columns. Poses are in the object frame, then mapped
into the world by the object pose. All randomness comes from one seeded
generator.
"""

from __future__ import annotations

import logging
import math
from pathlib import Path
from typing import Any

import numpy as np

from gcm_pipeline.errors import ConfigError, InputError
from gcm_pipeline.sources.grippers import GripperSpec

__all__ = ["DEFAULT_FRICTION", "antipodal_candidates", "object_mesh", "sample_antipodal"]

log = logging.getLogger(__name__)

#: Default friction coefficient of the contacts.
DEFAULT_FRICTION = 0.5
#: Opening kept free beyond the contact width [m].
_CLEARANCE = 0.005
_MIN_WIDTH = 0.002
#: Grasps whose hand is checked against object and table at once (their check
#: points take about 27 MB), so memory stays flat for any ``count``.
_CHUNK_POSES = 4096
#: Sampling stops once this many times ``count`` grasps are collision-free;
#: ``count`` of them are then drawn at random.
_POOL_FACTOR = 4
#: Most surface points drawn in one round.
_MAX_POINTS = 1_000_000


def object_mesh(
    shape: str,
    *,
    radius: float | None = None,
    height: float | None = None,
    size: tuple[float, ...] | None = None,
    mesh: str | Path | None = None,
    scale: float = 1.0,
) -> Any:
    """The object as a ``trimesh.Trimesh`` in its own frame (as the collision model has it).

    Cylinders stand on their base at z = 0; boxes and spheres are centred.

    Args:
        shape: ``cylinder``, ``box``, ``sphere``, ``mesh`` (or ``plane``: refused).
        radius: Cylinder or sphere radius [m].
        height: Cylinder height [m].
        size: Box size (x, y, z) [m].
        mesh: ``mesh``: the mesh file (``object.mesh``).
        scale: ``mesh``: scale applied to the file's vertices.

    Raises:
        ConfigError: A plane (no volume to grasp across).
        InputError: An unreadable or empty mesh file.
    """
    import trimesh

    # the config checked that the shape's dims are given
    if shape == "cylinder":
        assert radius is not None and height is not None
        solid = trimesh.creation.cylinder(radius=radius, height=height, sections=64)
        solid.apply_translation([0.0, 0.0, 0.5 * height])
        return solid
    if shape == "box":
        assert size is not None
        return trimesh.creation.box(extents=list(size))
    if shape == "sphere":
        assert radius is not None
        return trimesh.creation.icosphere(subdivisions=3, radius=radius)
    if shape == "plane":
        raise ConfigError(
            "candidates.source 'antipodal' needs a solid object; a plane has no two sides "
            "to close the fingers on (use source: plane)"
        )
    try:
        loaded = trimesh.load(str(mesh), force="mesh")
    except Exception as exc:  # trimesh raises many types for unreadable files
        raise InputError(f"object.mesh {mesh}: cannot read: {exc}") from None
    if not isinstance(loaded, trimesh.Trimesh) or len(loaded.faces) == 0:
        raise InputError(f"object.mesh {mesh}: no triangles")
    loaded.apply_scale(scale)
    if not loaded.is_watertight:
        log.warning(
            "object.mesh %s is not watertight (not a closed surface): the antipodal sampler's "
            "inside tests may be wrong, and the contact model cannot tell whether a gripper "
            "piece lies wholly inside it (collision checks see only crossings of its surface)",
            mesh,
        )
    elif loaded.volume < 0:  # faces wound inside out: normals point into the object
        log.info("object.mesh %s: faces wound inside out; turned", mesh)
        loaded.invert()
    return loaded


def _perpendicular_basis(d: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Two unit vectors (N, 3) completing the unit vectors ``d`` (N, 3) to a frame."""
    helper = np.where(np.abs(d[:, :1]) < 0.9, [[1.0, 0.0, 0.0]], [[0.0, 1.0, 0.0]])
    a = np.cross(d, helper)
    a /= np.linalg.norm(a, axis=1, keepdims=True)
    return a, np.cross(d, a)


def _in_cone(axis: np.ndarray, half_angle: float, rng: np.random.Generator) -> np.ndarray:
    """Unit directions (N, 3) uniform (in solid angle) inside cones around ``axis``."""
    n = len(axis)
    cos_t = 1.0 - rng.random(n) * (1.0 - math.cos(half_angle))
    sin_t = np.sqrt(np.clip(1.0 - cos_t**2, 0.0, None))
    phi = rng.uniform(0.0, 2 * math.pi, n)
    a, b = _perpendicular_basis(axis)
    return cos_t[:, None] * axis + sin_t[:, None] * (
        np.cos(phi)[:, None] * a + np.sin(phi)[:, None] * b
    )


def _gripper_points(gripper: GripperSpec) -> tuple[np.ndarray, np.ndarray]:
    """Check points on the open gripper in the grasp frame (tips at z = 0): fingers, palm."""
    w = 0.5 * gripper.max_width
    length = gripper.finger_length
    fingers = [
        [x, side * (w + f * gripper.finger_thickness), z]
        for side in (-1.0, 1.0)
        for f in (0.05, 0.5, 0.95)
        for x in np.linspace(-0.5, 0.5, 3) * gripper.finger_width
        for z in np.linspace(-length, gripper.finger_tip, 8)
    ]
    px, py, pz = gripper.palm_size
    palm = [
        [x, y, -length - z]
        for x in np.linspace(-0.5, 0.5, 3) * px
        for y in np.linspace(-0.5, 0.5, 15) * py
        for z in (0.001, 0.25 * pz, pz)
    ]
    return np.asarray(fingers), np.asarray(palm)


#: How far behind the palm the wrist and forearm reach along -z [m] (floor test only).
_ARM_BEHIND = 0.25


def _arm_points(gripper: GripperSpec) -> np.ndarray:
    """Points on the axis behind the palm (the wrist the arm holds the hand by)."""
    start = gripper.finger_length + gripper.palm_size[2]
    return np.array([[0.0, 0.0, -z] for z in np.linspace(start, start + _ARM_BEHIND, 6)])


def sample_antipodal(
    mesh: Any,
    count: int,
    gripper: GripperSpec,
    rng: np.random.Generator,
    *,
    friction: float = DEFAULT_FRICTION,
    approaches: int = 8,
    world: np.ndarray | None = None,
    floor_z: float | None = None,
) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    """Antipodal parallel-jaw grasps on a mesh (see the module docstring).

    Args:
        mesh: A ``trimesh.Trimesh`` (watertight for reliable inside tests).
        count: Number of grasps N wanted.
        gripper: Opening, finger and palm sizes.
        rng: Random generator.
        friction: Friction coefficient (cone half angle ``atan(friction)``).
        approaches: Approach directions tried per contact pair.
        world: Object pose in the world (4, 4), for ``floor_z``.
        floor_z: Grasps whose gripper reaches below this world height [m]
            (the table top) are dropped.

    Returns:
        ``(poses, columns)``: grasp frames (M, 4, 4) in the mesh frame with
        M <= N, and ``score``, ``width`` (M,).
    """
    half = math.atan(friction)
    cos_half = math.cos(half)
    checks = _gripper_points(gripper)
    arm = _arm_points(gripper)
    max_width = gripper.max_width - _CLEARANCE
    found: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = []
    total = 0
    n_points = min(max(100, 4 * count), _MAX_POINTS)
    for _ in range(10):  # more surface points while too few grasps survive
        pts, face = _sample_surface(mesh, n_points, rng)
        n1 = mesh.face_normals[face]
        d = _in_cone(-n1, half, rng)
        hit, ray, tri = mesh.ray.intersects_location(pts + 1e-6 * d, d, multiple_hits=False)
        if len(ray):
            p1, dd = pts[ray], d[ray]
            width = np.linalg.norm(hit - p1, axis=1)
            n2 = mesh.face_normals[tri]
            cos1 = np.einsum("ij,ij->i", dd, -n1[ray])
            cos2 = np.einsum("ij,ij->i", dd, n2)
            ok = (width > _MIN_WIDTH) & (width <= max_width) & (cos1 >= cos_half)
            ok &= cos2 >= cos_half
            sel = np.flatnonzero(ok)
            # enough pairs for the grasps still missing (a few of K approaches survive)
            cap = max(200, 4 * (count - total))
            if len(sel) > cap:
                sel = np.sort(rng.choice(sel, size=cap, replace=False))
            if len(sel):
                quality = np.minimum(cos1, cos2)[sel]
                phase = rng.uniform(0.0, 2 * math.pi, (len(sel), 1))
                step = max(1, _CHUNK_POSES // approaches)
                for start in range(0, len(sel), step):
                    part = sel[start : start + step]
                    poses, score, w = _frames(
                        p1[part],
                        hit[part],
                        dd[part],
                        quality[start : start + step],
                        gripper,
                        phase[start : start + step],
                        approaches,
                    )
                    keep = _collision_free(mesh, poses, checks, arm, world, floor_z)
                    found.append((poses[keep], score[keep], w[keep]))
                    total += int(keep.sum())
                    if total >= _POOL_FACTOR * count:
                        break
        if total >= count:
            break
        n_points = min(2 * n_points, _MAX_POINTS)
    if total == 0:
        return np.zeros((0, 4, 4)), {"score": np.zeros(0), "width": np.zeros(0)}
    poses = np.concatenate([f[0] for f in found])
    score = np.concatenate([f[1] for f in found])
    width = np.concatenate([f[2] for f in found])
    pick = np.sort(rng.choice(len(poses), size=min(count, len(poses)), replace=False))
    return poses[pick], {"score": score[pick], "width": width[pick]}


def _sample_surface(mesh: Any, n: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    import trimesh

    seed = int(rng.integers(0, 2**31 - 1))
    pts, face = trimesh.sample.sample_surface(mesh, n, seed=seed)
    return np.asarray(pts), np.asarray(face)


def _frames(
    p1: np.ndarray,
    p2: np.ndarray,
    d: np.ndarray,
    quality: np.ndarray,
    gripper: GripperSpec,
    phase: np.ndarray,
    approaches: int,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Grasp frames (P * K, 4, 4) around each contact axis, with score and width.

    The K approaches of a pair are evenly spaced from its ``phase`` (P, 1) [rad].
    """
    n, k = len(p1), approaches
    a, b = _perpendicular_basis(d)
    theta = phase + 2 * math.pi * np.arange(k) / k
    z = np.cos(theta)[..., None] * a[:, None] + np.sin(theta)[..., None] * b[:, None]
    y = np.broadcast_to(d[:, None], z.shape)
    x = np.cross(y, z)
    center = 0.5 * (p1 + p2)
    origin = center[:, None] + 0.5 * gripper.finger_depth * z
    poses = np.zeros((n, k, 4, 4))
    poses[..., :3, 0], poses[..., :3, 1], poses[..., :3, 2] = x, y, z
    poses[..., :3, 3] = origin
    poses[..., 3, 3] = 1.0
    width = np.linalg.norm(p2 - p1, axis=1)
    return poses.reshape(-1, 4, 4), np.repeat(quality, k), np.repeat(width, k)


def _collision_free(
    mesh: Any,
    poses: np.ndarray,
    checks: tuple[np.ndarray, ...],
    arm: np.ndarray,
    world: np.ndarray | None,
    floor_z: float | None,
) -> np.ndarray:
    """(M,) whether no gripper check point is below the floor or inside the mesh.

    The cheap floor test (hand and the ``arm`` points behind it) runs first,
    then the point sets in turn (fingers, then palm), each only on the grasps
    still free.
    """
    ok = np.ones(len(poses), dtype=bool)
    every = np.concatenate([*checks, arm])
    if floor_z is not None and world is not None:
        pts = np.einsum("mij,kj->mki", poses[:, :3, :3], every) + poses[:, None, :3, 3]
        ok &= (pts @ world[2, :3] + world[2, 3] >= floor_z).all(axis=1)
    for part in checks:
        idx = np.flatnonzero(ok)
        if idx.size == 0:
            break
        pts = np.einsum("mij,kj->mki", poses[idx, :3, :3], part) + poses[idx, None, :3, 3]
        inside = mesh.contains(pts.reshape(-1, 3)).reshape(len(idx), -1).any(axis=1)
        ok[idx[inside]] = False
    return ok


def antipodal_candidates(
    mesh: Any,
    count: int,
    gripper: GripperSpec,
    rng: np.random.Generator,
    *,
    shape: str,
    friction: float = DEFAULT_FRICTION,
    world: np.ndarray | None = None,
    floor_z: float | None = None,
) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    """:func:`sample_antipodal` as a candidate source: world poses and columns, or an error.

    Args:
        mesh: The object (:func:`object_mesh`) in its own frame.
        count: Number of grasps wanted.
        gripper: The gripper (``candidates.gripper``, else ``robot.tool``'s).
        rng: Random generator.
        shape: The object's shape (for the message).
        friction: Friction coefficient of the contacts.
        world: (4, 4) the object's pose in the world (default: identity).
        floor_z: Height of the table top in the world, if there is a table.

    Returns:
        ``(poses, columns)``: (M, 4, 4) grasp frames in the world, M <= ``count``.

    Raises:
        InputError: No antipodal grasp found.
        ConfigError: A gripper without fingers (a suction cup).
    """
    if gripper.kind != "parallel_jaw":
        raise ConfigError(
            f"candidates.source 'antipodal': gripper {gripper.name!r} is a {gripper.kind} "
            "gripper; the sampler places two fingers (a parallel_jaw gripper such as "
            "franka_panda, robotiq_2f_85, robotiq_2f_140)",
            key="candidates.gripper",
            value=gripper.name,
        )
    world = np.eye(4) if world is None else world
    poses, columns = sample_antipodal(
        mesh, count, gripper, rng, friction=friction, world=world, floor_z=floor_z
    )
    if len(poses) == 0:
        size = " x ".join(f"{1000 * e:.3g}" for e in mesh.extents)
        raise InputError(
            f"candidates.source 'antipodal': no collision-free antipodal grasp on the "
            f"{shape} object ({size} mm) for gripper {gripper.name!r}: the fingers need "
            f"two faces {1000 * _MIN_WIDTH:g} to {1000 * (gripper.max_width - _CLEARANCE):g} mm "
            f"apart, each within the friction cone (friction {friction:g}) of the closing "
            "direction, and room for the open hand outside the object and above the table"
        )
    if len(poses) < count:
        log.warning("antipodal: %d of %d grasps found", len(poses), count)
    return world @ poses, columns
