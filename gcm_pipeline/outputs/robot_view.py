"""The robot in the scene: its visual meshes (simplified, cached on disk), posed and animated.

Every object of the robot's visual ``GeometryModel`` is drawn under
``/robot/visuals/<name>``, posed by Pinocchio's forward kinematics at the
top-ranked solution; an animation steps through the top-k solutions,
blending on one IK branch and cutting across them (:func:`animation_keys`).
Robot meshes are read with trimesh, grouped by colour and simplified
(:func:`_simplified_mesh`), cached per file in :func:`mesh_cache_dir`.
"""

from __future__ import annotations

import contextlib
import functools
import hashlib
import os
import stat
import time
import warnings
from collections.abc import Sequence
from importlib.metadata import PackageNotFoundError, version
from pathlib import Path
from typing import Any

import coal
import numpy as np
import pinocchio as pin
import umsgpack

from gcm_pipeline.errors import InputError, OutputError, PublishError
from gcm_pipeline.outputs.meshcat_lib import load_meshcat
from gcm_pipeline.robot.model import Robot
from gcm_pipeline.rundir.arrays import read_npz
from gcm_pipeline.rundir.transaction import atomic_file

__all__ = [
    "ANIMATION_BLEND_LIMIT",
    "MESH_FACE_BUDGET",
    "ROT_X90",
    "RobotDrawer",
    "animation_keys",
    "mesh_cache_dir",
]
_ANIM_FPS = 30
_ANIM_HOLD = 15  # frames a solution is held [1/fps s]
_ANIM_MOVE = 9  # frames of joint-space interpolation to the next solution
#: Largest joint jump [rad] (L-infinity) the animation blends across: one IK branch
#: (the default ``continuity.threshold``); beyond it, the animation cuts.
ANIMATION_BLEND_LIMIT = 0.5

# three.js cameras look along -z with y up; meshcat's camera hangs under
# /Cameras/default/rotated, which rotates y-up into the world's z-up.
ROT_X90 = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])


class RobotDrawer:
    """The visual geometry of a :class:`Robot` under ``/robot/visuals/<name>``.

    Every object of the robot's visual ``GeometryModel`` is drawn (meshes,
    and primitives such as a tool built from boxes), posed by Pinocchio's
    forward kinematics. Meshes are read with trimesh (the scene graph of a
    COLLADA file baked in, as Pinocchio's own geometry loader reads it),
    grouped by material colour and simplified (:func:`_simplified_mesh`), so a
    scene embeds each robot mesh once, small.
    """

    def __init__(self, vis: Any, robot: Robot, base: np.ndarray) -> None:
        model = robot.model
        visual = _visual_model(robot)
        for obj in visual.geometryObjects:
            _draw_geometry(vis[f"robot/visuals/{obj.name}"], obj)
        vis["robot"].set_transform(base)
        self.vis = vis
        self.model = model
        self.visual = visual
        self.data = model.createData()
        self.vdata = pin.GeometryData(visual)

    def display(self, q: np.ndarray) -> None:
        """Pose the robot's visuals at ``q``."""
        for path, t in self.placements(q):
            self.vis[path].set_transform(t)

    def placements(self, q: np.ndarray) -> list[tuple[str, np.ndarray]]:
        """Scene path and transform (4, 4) of every visual object at ``q``."""
        pin.forwardKinematics(self.model, self.data, q)
        pin.updateGeometryPlacements(self.model, self.data, self.visual, self.vdata)
        out = []
        for gid, obj in enumerate(self.visual.geometryObjects):
            t = self.vdata.oMg[gid].homogeneous.copy()
            t[:3, :3] = t[:3, :3] * np.asarray(obj.meshScale)[None, :]
            out.append((f"robot/visuals/{obj.name}", t))
        return out

    def joint_points(self, q: np.ndarray, base: np.ndarray) -> np.ndarray:
        """World positions (J, 3) of the robot's joint origins at ``q`` (for framing)."""
        pin.forwardKinematics(self.model, self.data, q)
        pts = np.array([m.translation for m in self.data.oMi])
        return pts @ base[:3, :3].T + base[:3, 3]

    def animate(
        self, vis: Any, qs: np.ndarray, blend_limit: float = ANIMATION_BLEND_LIMIT
    ) -> tuple[float, int]:
        """Set the top-k animation (:func:`animation_keys`); its duration [s] and cuts."""
        anim = load_meshcat().animation.Animation(default_framerate=_ANIM_FPS)
        keys, cuts = animation_keys(qs, blend_limit)
        for frame, q in keys:
            self._keyframe(anim, vis, frame, q)
        vis.set_animation(anim, play=True, repetitions=1)
        return (keys[-1][0] + 1) / _ANIM_FPS, cuts

    def _keyframe(self, anim: Any, vis: Any, frame: int, q: np.ndarray) -> None:
        with anim.at_frame(vis, frame) as f:
            for path, t in self.placements(q):
                f[path].set_transform(t)


def animation_keys(
    qs: np.ndarray, blend_limit: float = ANIMATION_BLEND_LIMIT
) -> tuple[list[tuple[int, np.ndarray]], int]:
    """Keyframes of the top-k animation: each solution held, then the next one.

    Two consecutive solutions (and the last and the first, which closes the
    loop) within ``blend_limit`` [rad] of each other in every joint are on one
    IK branch: the animation blends between them in joint space. Farther apart
    they are on different branches, and a joint-space blend would swing the arm
    through poses nobody checked: the animation **cuts**, keying the next
    solution on the very next frame, with no configuration in between.

    Args:
        qs: (k, nq) solutions, best first.
        blend_limit: Largest joint jump [rad] (L-infinity) blended across.

    Returns:
        ``(frame, q)`` keyframes in frame order, and the number of cuts.
    """
    qs = np.asarray(qs, dtype=float)
    seq = [*qs, qs[0]] if len(qs) > 1 else list(qs)
    keys: list[tuple[int, np.ndarray]] = []
    frame = 0
    cuts = 0
    for i, q in enumerate(seq):
        if i > 0:
            prev = seq[i - 1]
            if np.max(np.abs(q - prev), initial=0.0) <= blend_limit:
                for s in range(1, _ANIM_MOVE):
                    keys.append((frame, prev + (q - prev) * (s / _ANIM_MOVE)))
                    frame += 1
            else:
                cuts += 1
        keys.append((frame, q))
        frame += _ANIM_HOLD
        keys.append((frame, q))
        frame += 1
    return keys, cuts


# -- robot meshes -----------------------------------------------------------------------

#: Faces kept per visual object of the robot (its colour groups share them).
MESH_FACE_BUDGET = 6000
#: Colour groups with fewer faces than this are kept as they are.
_MIN_SIMPLIFY_FACES = 300


def packed_mesh(vertices: np.ndarray, faces: np.ndarray) -> Any:
    """A three.js ``BufferGeometry``: float32 positions (V, 3), a uint16 (or uint32) index (F, 3).

    A meshcat ``Geometry`` (the class is made on first use, when meshcat loads).
    The viewer computes vertex normals for a geometry without them.
    """
    return _packed_mesh_class()(vertices, faces)


@functools.cache
def _packed_mesh_class() -> type:
    """The class of :func:`packed_mesh`, made once meshcat (its base class) is loaded."""
    mg = load_meshcat().geometry

    class PackedMesh(mg.Geometry):
        """A three.js ``BufferGeometry``: float32 positions, a uint16 (or uint32) index.

        The viewer computes vertex normals for a geometry without them.
        """

        def __init__(self, vertices: np.ndarray, faces: np.ndarray) -> None:
            super().__init__()
            self.vertices = np.ascontiguousarray(vertices, dtype=np.float32)
            small = len(self.vertices) < 65536
            self.faces = np.ascontiguousarray(faces, dtype=np.uint16 if small else np.uint32)

        def lower(self, object_data: Any) -> dict[str, Any]:
            index_type, code = (
                ("Uint16Array", 20) if self.faces.dtype == np.uint16 else ("Uint32Array", 22)
            )
            return {
                "uuid": self.uuid,
                "type": "BufferGeometry",
                "data": {
                    "attributes": {
                        "position": {
                            "itemSize": 3,
                            "type": "Float32Array",
                            "array": umsgpack.Ext(23, self.vertices.tobytes()),
                            "normalized": False,
                        }
                    },
                    "index": {
                        "itemSize": 1,
                        "type": index_type,
                        "array": umsgpack.Ext(code, self.faces.tobytes()),
                        "normalized": False,
                    },
                },
            }

    return PackedMesh


#: Version of the simplified-mesh cache files (bump when their content changes).
_MESH_CACHE_VERSION = 1


def mesh_cache_dir() -> Path:
    """Folder of the simplified robot meshes: ``$GCM_CACHE_DIR/meshes``.

    ``GCM_CACHE_DIR`` defaults to ``$XDG_CACHE_HOME/gcm_pipeline`` (``~/.cache/gcm_pipeline``).
    Deleting it is always safe: the meshes are simplified again on the next run.
    """
    root = os.environ.get("GCM_CACHE_DIR")
    if not root:
        xdg = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
        root = os.path.join(xdg, "gcm_pipeline")
    return Path(root) / "meshes"


def _simplified_mesh(path: str, budget: int = MESH_FACE_BUDGET) -> list[tuple[int, Any]]:
    """A mesh file as (colour 0xRRGGBB, packed geometry) groups, at most ~``budget`` faces.

    Reading a robot's COLLADA files and simplifying them takes about a second
    for the Panda, so the result is cached per file (path, modification time,
    size) for the process and on disk (:func:`mesh_cache_dir`, keyed by the
    file's content and the budget).
    """
    st = os.stat(path)
    return _simplified_mesh_cached(path, st.st_mtime_ns, st.st_size, budget)


@functools.lru_cache(maxsize=64)
def _simplified_mesh_cached(
    path: str, _mtime: int, _size: int, budget: int
) -> list[tuple[int, Any]]:
    try:
        data = Path(path).read_bytes()
    except OSError as exc:
        raise PublishError(f"cannot read robot mesh {path!r}: {exc}") from exc
    # the mesh's bytes, its material files (an .obj's mtllib: its colours) and the
    # libraries that read and simplify it (an upgrade may simplify differently)
    digest = hashlib.sha256(data + _simplifier_versions().encode())
    for material in _material_files(Path(path), data):
        with contextlib.suppress(OSError):
            digest.update(material.read_bytes())
    key = digest.hexdigest()[:32]
    cache = mesh_cache_dir() / f"{key}-b{budget}-v{_MESH_CACHE_VERSION}.npz"
    groups = _read_mesh_cache(cache)
    if groups is None:
        groups = _simplify_mesh(path, budget)
        _write_mesh_cache(cache, groups)
    return [(color, packed_mesh(verts, faces)) for color, verts, faces in groups]


_MeshGroups = list[tuple[int, np.ndarray, np.ndarray]]


@functools.cache
def _simplifier_versions() -> str:
    """Versions of the libraries behind :func:`_simplify_mesh`, for the cache key."""
    out = []
    for dist in ("trimesh", "fast-simplification", "numpy"):
        try:
            out.append(f"{dist}={version(dist)}")
        except PackageNotFoundError:
            out.append(f"{dist}=?")
    return ";".join(out)


def _read_mesh_cache(path: Path) -> _MeshGroups | None:
    """The groups of a cache file, or None when it is absent or unreadable.

    Only a regular file is opened (a named pipe there would block), and the
    arrays its headers declare must fit in the file (the cache is written
    uncompressed) before anything is allocated: a header claiming a terabyte
    is a damaged entry, simplified again.
    """
    try:
        st = os.stat(path)
        if not stat.S_ISREG(st.st_mode):
            return None
        z = read_npz(path, max_bytes=st.st_size)
    except (OSError, InputError):
        return None
    try:
        colors = np.asarray(z["colors"], dtype=np.int64)
        if colors.ndim != 1:
            return None
        groups = [
            (int(c), np.asarray(z[f"v{i}"], dtype=np.float32), np.asarray(z[f"f{i}"]))
            for i, c in enumerate(colors.tolist())
        ]
    except (ValueError, TypeError, KeyError, OverflowError):
        return None
    for _, verts, faces in groups:
        if (
            verts.ndim != 2
            or verts.shape[1:] != (3,)
            or faces.ndim != 2
            or faces.shape[1:] != (3,)
            or not np.issubdtype(faces.dtype, np.integer)
            or (faces.size and (faces.min() < 0 or faces.max() >= len(verts)))
            or not np.isfinite(verts).all()
        ):
            return None
    return groups


def _write_mesh_cache(path: Path, groups: _MeshGroups) -> None:
    """Store ``groups`` atomically; a cache that cannot be written is skipped."""
    arrays: dict[str, Any] = {"colors": np.array([c for c, _, _ in groups], np.int64)}
    for i, (_, verts, faces) in enumerate(groups):
        arrays[f"v{i}"] = np.asarray(verts, dtype=np.float32)
        arrays[f"f{i}"] = np.asarray(faces, dtype=np.uint32)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        _remove_stale_tmp(path.parent)
        with atomic_file(path) as tmp, open(tmp, "wb") as fh:
            np.savez(fh, **arrays)
    except (OSError, OutputError):
        pass


def _material_files(path: Path, data: bytes) -> list[Path]:
    """The material files an .obj mesh names (``mtllib`` lines), beside it."""
    if path.suffix.lower() != ".obj":
        return []
    out = []
    for line in data.splitlines():
        if line.startswith(b"mtllib"):
            name = line[len(b"mtllib") :].strip().decode("utf-8", "replace")
            if name:
                out.append(path.parent / name)
    return out


#: A cache file still being written after this long was left by a killed process [s].
_STALE_TMP_S = 3600.0


def _remove_stale_tmp(folder: Path) -> None:
    """Delete the cache's temporary files left by processes killed while writing."""
    now = time.time()
    for left in folder.glob(".*.tmp"):
        with contextlib.suppress(OSError):
            if now - left.stat().st_mtime > _STALE_TMP_S:
                left.unlink()


def _simplify_mesh(path: str, budget: int) -> _MeshGroups:
    """Read a mesh file with trimesh, group it by colour and simplify each group."""
    import fast_simplification
    import trimesh

    try:
        scene: Any = trimesh.load(path, force="scene")
    except Exception as exc:  # trimesh raises many types for unreadable files
        raise PublishError(f"cannot read robot mesh {path!r}: {exc}") from exc
    groups: dict[int, list[np.ndarray]] = {}
    faces_by: dict[int, list[np.ndarray]] = {}
    offsets: dict[int, int] = {}
    for node in scene.graph.nodes_geometry:
        transform, name = scene.graph[node]
        geom = scene.geometry[name]
        if not isinstance(geom, trimesh.Trimesh) or len(geom.faces) == 0:
            continue
        color = _mesh_color(geom)
        verts = trimesh.transform_points(geom.vertices, transform)
        groups.setdefault(color, []).append(verts)
        faces_by.setdefault(color, []).append(np.asarray(geom.faces) + offsets.get(color, 0))
        offsets[color] = offsets.get(color, 0) + len(verts)
    total = sum(len(f) for fs in faces_by.values() for f in fs)
    out = []
    for color, parts in groups.items():
        verts = np.concatenate(parts)
        faces = np.concatenate(faces_by[color])
        mesh = trimesh.Trimesh(verts, faces, process=True)
        verts, faces = np.asarray(mesh.vertices), np.asarray(mesh.faces)
        keep = max(_MIN_SIMPLIFY_FACES, int(budget * len(faces) / max(total, 1)))
        if len(faces) > keep:
            verts, faces = fast_simplification.simplify(verts, faces, 1.0 - keep / len(faces))
        out.append((color, np.asarray(verts, dtype=np.float32), np.asarray(faces)))
    return out


def _mesh_color(geom: Any) -> int:
    """The main colour of a trimesh geometry as 0xRRGGBB (its material or first face colour)."""
    visual = geom.visual
    rgba = None
    material = getattr(visual, "material", None)
    if material is not None:
        rgba = getattr(material, "main_color", None)
    if rgba is None and getattr(visual, "kind", None) in ("face", "vertex"):
        colors = visual.face_colors if visual.kind == "face" else visual.vertex_colors
        rgba = colors[0] if len(colors) else None
    if rgba is None:
        return 0xB3B3B3
    r, g, b = (int(c) for c in np.asarray(rgba)[:3])
    return (r << 16) | (g << 8) | b


def _rgba_hex(rgba: Sequence[float]) -> int:
    r, g, b = (int(round(255 * float(c))) for c in rgba[:3])
    return (r << 16) | (g << 8) | b


def _draw_geometry(node: Any, obj: Any) -> None:
    """Draw one visual ``GeometryObject`` under ``node`` (meshes and coal primitives)."""
    mg = load_meshcat().geometry
    geom = obj.geometry
    color = _rgba_hex(obj.meshColor) if obj.overrideMaterial else None
    opacity = float(obj.meshColor[3]) if obj.overrideMaterial else 1.0

    def material(c: int) -> Any:
        kw = {"opacity": opacity, "transparent": opacity < 1.0}
        return mg.MeshPhongMaterial(color=c, **kw)

    default = (
        color
        if color is not None
        else _rgba_hex(obj.meshColor)
        if any(obj.meshColor[:3])
        else 0xB3B3B3
    )
    if isinstance(geom, coal.Box):
        node["0"].set_object(mg.Box((2.0 * np.asarray(geom.halfSide)).tolist()), material(default))
    elif isinstance(geom, coal.Sphere):
        node["0"].set_object(mg.Sphere(float(geom.radius)), material(default))
    elif isinstance(geom, coal.Cylinder):
        node["0"].set_object(mg.Cylinder(2.0 * geom.halfLength, geom.radius), material(default))
        local = np.eye(4)
        local[:3, :3] = ROT_X90  # meshcat cylinders run along y, coal's along z
        node["0"].set_transform(local)
    elif obj.meshPath and Path(obj.meshPath).is_file():
        for k, (c, mesh) in enumerate(_simplified_mesh(obj.meshPath)):
            node[str(k)].set_object(mesh, material(color if color is not None else c))
    elif hasattr(geom, "num_tris") and geom.num_tris > 0:  # a mesh built in memory
        verts = np.array([geom.vertices(i) for i in range(geom.num_vertices)])
        tris = np.array([list(geom.tri_indices(i)) for i in range(geom.num_tris)])
        node["0"].set_object(packed_mesh(verts, tris), material(default))
    else:
        warnings.warn(
            f"robot visual {obj.name!r}: geometry {type(geom).__name__} is not drawn",
            stacklevel=3,
        )


def _visual_model(robot: Robot) -> Any:
    """The robot's visual GeometryModel, reduced like its kinematic model."""
    build = getattr(robot, "build_geometry", None)
    if build is not None:
        return build("visual")
    vm = getattr(robot, "visual_model", None)  # e.g. a pinocchio RobotWrapper
    if vm is not None:
        return vm
    raise PublishError(f"robot {robot!r} offers no visual geometry (build_geometry('visual'))")
