"""The object a grasp file names: its mesh found under a root folder, stood on the table.

ACRONYM's HDF5 files (``object/file``, ``object/scale``) and GraspGen's
dataset files (``object.file``, ``object.scale``) name the mesh their grasps
were made on; the grasps are poses in that mesh's frame, scaled by the file's
scale. :func:`named_object` reads the two, :func:`find_mesh` resolves the
name against a root folder (ACRONYM's layout by default: the name is relative
to the folder that holds ``meshes/``, i.e. the parent of the grasp file's
folder), and :func:`stable_placement` stands the scaled mesh on the table in
one of its stable poses (:func:`trimesh.poses.compute_stable_poses`; by
default the upright one, else by index, the most probable first) at a given
x, y and yaw. The mesh's pose in the world is then
the object pose of the grasps (``frame: object``): they move with it.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import trimesh

from gcm_pipeline.errors import InputError, clip
from gcm_pipeline.sources.files.acronym import read_acronym, read_acronym_object
from gcm_pipeline.sources.files.graspgen import graspgen_object

__all__ = [
    "MESH_KEYS",
    "Placement",
    "find_mesh",
    "load_scaled",
    "named_object",
    "stable_placement",
    "warn_if_open",
]

log = logging.getLogger(__name__)

#: Formats whose files can name the object mesh, and the key that names it.
MESH_KEYS = {"acronym": "object/file", "graspgen": "object.file"}


def named_object(path: Path, fmt: str | None, max_count: int) -> tuple[str | None, float]:
    """The mesh a grasp file names (None when it names none) and the file's scale.

    Raises:
        InputError: An unreadable file, or a scale that is not a positive finite number.
    """
    if fmt == "acronym":
        read_acronym(path, max_count)  # in a child process: a corrupt file cannot crash us
        return read_acronym_object(path)
    if fmt == "graspgen":
        return graspgen_object(path, max_count)
    return None, 1.0


def find_mesh(grasp_file: Path, name: str, fmt: str, root: Path | None) -> Path:
    """The mesh file ``name`` (as the grasp file stores it) under ``root``.

    Tried in order: ``root / name`` and ``root / basename(name)`` when a
    root is given; else ``grasp_file``'s folder's parent ``/ name`` (ACRONYM's
    layout: ``grasps/`` beside ``meshes/``), the grasp file's folder ``/ name``
    and ``/ basename(name)`` (a mesh downloaded beside the grasp file).

    Raises:
        InputError: None of them is a file; names the grasp file, its key and
            every path tried (key ``candidates.mesh_root``).
    """
    rel = Path(name)
    if rel.is_absolute():
        tried = [rel]
    elif root is not None:
        tried = [root / rel, root / rel.name]
    else:
        folder = grasp_file.parent
        tried = [folder.parent / rel, folder / rel, folder / rel.name]
    tried = list(dict.fromkeys(tried))
    for p in tried:
        try:
            if p.is_file():
                return p
        except (OSError, ValueError):
            continue
    where = (
        "candidates.mesh_root" if root is not None else "the default root (candidates.mesh_root)"
    )
    raise InputError(
        f"{grasp_file}: {MESH_KEYS[fmt]} {clip(name)}: mesh not found under {where}; tried "
        + ", ".join(str(p) for p in tried)
        + "; set candidates.mesh_root to the folder that holds it, or give an 'object' section",
        path=grasp_file,
        key="candidates.mesh_root",
        value=name,
    )


@dataclass(frozen=True)
class Placement:
    """A mesh stood on the table.

    Attributes:
        pose: (4, 4) the mesh frame in the world (the mesh scaled by ``scale`` first).
        index: Which stable pose, by probability (0: the most probable).
        probability: Its probability (trimesh's quasi-static estimate).
        count: How many stable poses the mesh has.
        watertight: Whether the mesh is closed.
    """

    pose: np.ndarray
    index: int
    probability: float
    count: int
    watertight: bool


def load_scaled(mesh_path: Path, scale: float, what: str) -> Any:
    """The mesh file as a ``trimesh.Trimesh`` scaled to metres.

    Args:
        mesh_path: The mesh file.
        scale: Its scale (file units -> metres).
        what: How messages name it (e.g. ``<grasp file>: object/file -> <mesh>``).

    Raises:
        InputError: Unreadable, no triangles, or a vertex that is not finite (names ``what``).
    """
    try:
        mesh = trimesh.load(str(mesh_path), force="mesh")
    except Exception as exc:  # trimesh raises many types for unreadable files
        raise InputError(
            f"{what}: cannot read the mesh: {clip(str(exc))}", path=mesh_path
        ) from None
    if not isinstance(mesh, trimesh.Trimesh) or len(mesh.faces) == 0:
        raise InputError(f"{what}: the mesh has no triangles", path=mesh_path)
    if not np.isfinite(mesh.vertices).all():
        raise InputError(f"{what}: the mesh has a vertex that is not finite", path=mesh_path)
    mesh.apply_scale(scale)
    return mesh


def stable_placement(
    mesh: Any, xy: tuple[float, float], yaw: float, table_z: float, index: int | None, what: str
) -> Placement:
    """Stand ``mesh`` (scaled, in its own frame) on the plane ``z = table_z``.

    The mesh rests in one of its stable poses (trimesh's, ranked by
    probability, most probable first): number ``index``, or for None the
    upright one, whose up is nearest the mesh's own +z (the pose it was
    modelled in: ACRONYM's meshes are z-up, and a mug's most probable pose is on
    its side). It is turned by ``yaw`` [rad] about the vertical, with the
    centre of its footprint (the xy bounding box of the resting mesh before
    the yaw) at ``xy`` and its lowest point on the table. At ``yaw`` 0 the
    mesh's x axis, projected on the table, points along the world's x (its y
    axis when x points up or down).

    Raises:
        InputError: ``index`` is not below the number of stable poses (key
            ``candidates.placement.stable_pose``), or the mesh is flat (no
            stable pose).
    """
    watertight = bool(mesh.is_watertight)
    # an open mesh has no volume to weigh: its convex hull's centre of mass stands in
    try:
        com = mesh.center_mass if watertight else mesh.convex_hull.center_mass
        transforms, probs = trimesh.poses.compute_stable_poses(mesh, center_mass=com)
    except Exception as exc:  # qhull on a flat or degenerate mesh
        raise InputError(
            f"{what}: the mesh has no stable pose on a table (flat or degenerate: "
            f"{clip(' '.join(str(exc).split()))})",
        ) from None
    order = np.argsort(-np.asarray(probs), kind="stable")
    transforms = np.asarray(transforms, dtype=float)[order]
    if index is None:  # the mesh's +z in each resting pose is row 2 of its rotation
        index = int(np.argmax(transforms[:, 2, 2]))
        tilt = math.degrees(math.acos(min(1.0, float(transforms[index, 2, 2]))))
        if tilt > 1.0:
            log.info("%s: the upright stable pose tilts the mesh's z by %.1f deg", what, tilt)
    elif index >= len(order):
        raise InputError(
            f"candidates.placement.stable_pose: {index} is out of range; the mesh of {what} "
            f"has {len(order)} stable poses (0 to {len(order) - 1})",
            key="candidates.placement.stable_pose",
            value=index,
        )
    rest = _heading_zero(transforms[index])
    verts = mesh.vertices @ rest[:3, :3].T + rest[:3, 3]
    lo, hi = verts.min(axis=0), verts.max(axis=0)
    centre = np.array([(lo[0] + hi[0]) / 2, (lo[1] + hi[1]) / 2, lo[2]])
    c, s = math.cos(yaw), math.sin(yaw)
    turn = np.eye(4)
    turn[:2, :2] = [[c, -s], [s, c]]
    turn[:3, 3] = [xy[0], xy[1], table_z]
    shift = np.eye(4)
    shift[:3, 3] = -centre
    pose = turn @ shift @ rest
    return Placement(pose, index, float(probs[order[index]]), len(order), watertight)


def _heading_zero(rest: np.ndarray) -> np.ndarray:
    """``rest`` turned about the vertical so the mesh's x axis points along the world's x.

    Trimesh's stable poses come with an arbitrary turn about the vertical;
    this one makes ``yaw`` mean the same for every pose. When the mesh's x
    axis is (nearly) vertical its y axis sets the heading (along the world's y).
    """
    ax, ay = rest[:3, 0], rest[:3, 1]
    if math.hypot(ax[0], ax[1]) > 0.1:
        psi = math.atan2(ax[1], ax[0])
    else:
        psi = math.atan2(ay[1], ay[0]) - math.pi / 2
    c, s = math.cos(-psi), math.sin(-psi)
    turn = np.eye(4)
    turn[:2, :2] = [[c, -s], [s, c]]
    return turn @ rest


def warn_if_open(mesh_path: Path, scale: float, what: str) -> bool:
    """Warn once when the object mesh is not watertight; whether it is closed.

    The contact model (:mod:`gcm_pipeline.robot.collision.contact`) decides
    that a gripper piece lies wholly inside a mesh object by a winding-number
    inside test, and the antipodal sampler rejects fingers inside the object the
    same way: both need a closed surface. On an open mesh only crossings of its
    surface are seen. A mesh that cannot be read is left to the caller.
    """
    try:
        mesh = load_scaled(mesh_path, scale, what)
    except InputError:
        return True
    if mesh.is_watertight:
        return True
    log.warning(
        "%s: the mesh is not watertight (not a closed surface): the contact model cannot "
        "tell whether a gripper piece lies wholly inside it (collision checks see only "
        "crossings of its surface), and the antipodal sampler's inside tests may be wrong",
        what,
    )
    return False
