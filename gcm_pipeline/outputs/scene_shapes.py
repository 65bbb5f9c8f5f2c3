"""The object and the environment in the scene: shapes as meshcat geometry.

:class:`SceneShape` and :class:`SceneTable` are the plain values the scene
takes (``gcm_pipeline.pipeline`` maps the config's ``object`` and
``environment`` onto them); :func:`shape_view` is the scene's one per-shape
table.
"""

from __future__ import annotations

import warnings
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from gcm_pipeline.errors import PublishError
from gcm_pipeline.outputs.meshcat_lib import load_meshcat
from gcm_pipeline.outputs.robot_view import ROT_X90

__all__ = [
    "OBJECT_COLOR",
    "TABLE_COLOR",
    "SceneShape",
    "SceneTable",
    "draw_environment",
    "draw_object",
    "object_points",
    "shape_view",
    "translation",
]


#: Colour of the object (0xRRGGBB).
OBJECT_COLOR = 0xD9A441
#: Colour of the support table (0xRRGGBB).
TABLE_COLOR = 0xC8C3BA


@dataclass(frozen=True, eq=False)
class SceneShape:
    """A primitive or mesh placed in the world: the object or an obstacle.

    Attributes:
        shape: ``cylinder`` (standing on its base along the frame's z), ``box``,
            ``sphere`` (centred), ``plane`` (in the frame's xy plane) or ``mesh``.
        pose: The shape's frame in the world (4, 4) [m].
        radius: Cylinder and sphere radius [m].
        height: Cylinder height [m].
        size: Box (3) or plane (2) edge lengths [m].
        mesh: A ``mesh`` shape's file (.stl, .obj, .dae).
        scale: A ``mesh`` shape's scale factor.
        name: An obstacle's name (its scene path); None: ``obstacle_<i>``.
    """

    shape: str
    pose: np.ndarray
    radius: float | None = None
    height: float | None = None
    size: tuple[float, ...] | None = None
    mesh: Path | None = None
    scale: float = 1.0
    name: str | None = None

    def __post_init__(self) -> None:
        pose = np.array(self.pose, dtype=float)
        pose.setflags(write=False)
        object.__setattr__(self, "pose", pose)


@dataclass(frozen=True)
class SceneTable:
    """The support table: a box whose top face is at ``height`` [m] in the world.

    Attributes:
        height: Height of the top face [m].
        size: Edge lengths (x, y, thickness) [m].
        center_xy: Centre of the top face in the world's xy plane [m].
    """

    height: float = 0.0
    size: tuple[float, float, float] = (2.0, 2.0, 0.05)
    center_xy: tuple[float, float] = (0.0, 0.0)


def translation(xyz: Sequence[float]) -> np.ndarray:
    """The (4, 4) transform of a translation [m]."""
    m = np.eye(4)
    m[:3, 3] = xyz
    return m


def shape_view(obj: SceneShape, *, load_mesh: bool = True) -> tuple[Any, np.ndarray, np.ndarray]:
    """The scene's one per-shape table: a shape as meshcat geometry and points.

    ``obj`` is the object or an obstacle; every branch on the shape kind in
    this package's scene is here.

    Args:
        obj: The shape.
        load_mesh: Read a ``mesh`` shape's file (False: geometry None, for
            the points alone).

    Returns:
        The meshcat geometry, its transform (4, 4) in the shape's frame, and
        a few points (K, 3) in the shape's frame spanning it (for framing the
        camera; a mesh's bounding-box corners).

    Raises:
        PublishError: A mesh file that does not exist or has an unsupported format.
    """
    mg = load_meshcat().geometry
    shape = obj.shape
    if shape == "cylinder":
        r, h = obj.radius, obj.height
        # meshcat cylinders run along y, centred: stand it on its base along z
        local = translation((0.0, 0.0, h / 2.0))
        local[:3, :3] = ROT_X90
        return mg.Cylinder(h, r), local, np.array([[-r, -r, 0.0], [r, r, h]])
    if shape in ("box", "plane"):
        size = np.zeros(3)
        size[: len(obj.size)] = obj.size
        corners = np.array([-size / 2, size / 2])
        if shape == "box":
            return mg.Box(list(obj.size)), np.eye(4), corners
        # a thin box centred on the frame, as the collision world models it
        sx, sy = obj.size
        return mg.Box([sx, sy, 0.002]), np.eye(4), corners
    if shape == "sphere":
        r = obj.radius
        return mg.Sphere(r), np.eye(4), np.array([[-r] * 3, [r] * 3])
    # mesh
    if not load_mesh:
        return None, np.eye(4), _mesh_corners(Path(obj.mesh), obj.scale)
    path = Path(obj.mesh)
    if not path.is_file():
        raise PublishError(f"object mesh {str(path)!r} does not exist")
    ext = path.suffix.lower()
    loaders = {
        ".stl": mg.StlMeshGeometry.from_file,
        ".obj": mg.ObjMeshGeometry.from_file,
        ".dae": mg.DaeMeshGeometry.from_file,
    }
    if ext not in loaders:
        raise PublishError(
            f"object mesh {str(path)!r}: unsupported format {ext!r}; valid: .dae, .obj, .stl"
        )
    local = np.diag([obj.scale, obj.scale, obj.scale, 1.0])
    return loaders[ext](str(path)), local, _mesh_corners(path, obj.scale)


def _mesh_corners(path: Path, scale: float) -> np.ndarray:
    """The corners (8, 3) of a mesh file's bounding box, scaled [m, mesh frame].

    A mesh's origin can lie far from its geometry (ACRONYM's table: 2.7 m);
    the camera frames these corners. The origin alone (1, 3) when the file
    cannot be read.
    """
    try:
        import trimesh

        mesh: Any = trimesh.load(str(path), force="mesh", process=False)
        lo, hi = np.asarray(mesh.bounds, dtype=float) * scale
    except Exception:  # drawing the mesh reports an unreadable file
        return np.zeros((1, 3))
    if not (np.isfinite(lo).all() and np.isfinite(hi).all()):
        return np.zeros((1, 3))
    return np.array(
        [[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])]
    )


def object_points(obj: SceneShape) -> np.ndarray:
    """A few world points (K, 3) spanning the object (for framing the camera)."""
    local = shape_view(obj, load_mesh=False)[2]
    m = obj.pose
    return local @ m[:3, :3].T + m[:3, 3]


def draw_object(vis: Any, obj: SceneShape) -> list[str]:
    """Draw the grasped object under ``/object``; the scene paths drawn."""
    mg = load_meshcat().geometry
    geometry, local, _ = shape_view(obj)
    material = mg.MeshPhongMaterial(color=OBJECT_COLOR, opacity=0.7, transparent=True)
    vis["object"].set_transform(obj.pose)
    vis["object/shape"].set_object(geometry, material)
    vis["object/shape"].set_transform(local)
    return ["/object"]


def draw_environment(
    vis: Any, table: SceneTable | None, obstacles: Sequence[SceneShape]
) -> tuple[list[str], int]:
    """Draw the support table and the obstacles; the scene paths and the shapes drawn."""
    mg = load_meshcat().geometry
    paths: list[str] = []
    drawn = 0
    if table is not None:
        sx, sy, sz = table.size
        cx, cy = table.center_xy
        material = mg.MeshLambertMaterial(color=TABLE_COLOR)
        vis["environment/table"].set_object(mg.Box([sx, sy, sz]), material)
        vis["environment/table"].set_transform(translation((cx, cy, table.height - sz / 2)))
        # the table replaces meshcat's grid, which would z-fight with its top
        vis["/Grid"].set_property("visible", False)
        vis["/Axes"].set_property("visible", False)
        paths.append("/environment")
        drawn += 1
    for i, obs in enumerate(obstacles):
        if obs.shape == "mesh" and (obs.mesh is None or not Path(obs.mesh).is_file()):
            warnings.warn(f"obstacle {i}: mesh {obs.mesh} not found; not drawn", stacklevel=3)
            continue
        geometry, local, _ = shape_view(obs)
        name = obs.name or f"obstacle_{i}"
        material = mg.MeshLambertMaterial(color=0x8C8C99, opacity=0.7, transparent=True)
        vis[f"environment/{name}"].set_transform(obs.pose)
        vis[f"environment/{name}/shape"].set_object(geometry, material)
        vis[f"environment/{name}/shape"].set_transform(local)
        drawn += 1
        if "/environment" not in paths:
            paths.append("/environment")
    return paths, drawn
