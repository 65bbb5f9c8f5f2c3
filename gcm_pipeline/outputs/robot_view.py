"""The robot in the scene: its visual meshes (simplified, cached on disk), posed and animated.

Every object of the robot's visual ``GeometryModel`` is drawn under
``/robot/visuals/<name>``, posed by Pinocchio's forward kinematics at the
top-ranked solution; the top-k tour shows each solution's approach, the grasp
and its retreat, and cuts between grasps, never blending across them
(:func:`tour_keys`). :func:`kinematic_tree` exports the kinematics for the
page's own forward kinematics (:mod:`gcm_pipeline.outputs.scene_page`).
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
from dataclasses import dataclass
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
    "RobotPoser",
    "Tour",
    "TourSegment",
    "kinematic_tree",
    "tour_keys",
    "mesh_cache_dir",
]
_ANIM_FPS = 30
_ANIM_HOLD = 15  # frames a grasp is held [1/fps s]
_ANIM_MOVE = 15  # frames of an approach or a retreat (joint-space interpolation)
_ANIM_REST = 6  # frames the pre-grasp and the retreat's end are held
#: Largest joint jump [rad] (L-infinity) an approach or a retreat is interpolated
#: across: one IK branch (the default ``continuity.threshold``); beyond it, a cut.
ANIMATION_BLEND_LIMIT = 0.5

# three.js cameras look along -z with y up; meshcat's camera hangs under
# /Cameras/default/rotated, which rotates y-up into the world's z-up.
ROT_X90 = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])


class RobotPoser:
    """Poses of a :class:`Robot`'s visual objects: Pinocchio's forward kinematics, no drawing.

    The scene paths are ``robot/visuals/<name>`` (relative to the meshcat root),
    in the ``/robot`` frame (which carries the robot's base pose).
    """

    def __init__(self, robot: Robot) -> None:
        self.model = robot.model
        self.visual = _visual_model(robot)
        self.data = self.model.createData()
        self.vdata = pin.GeometryData(self.visual)

    def placements(self, q: np.ndarray, scaled: bool = True) -> list[tuple[str, np.ndarray]]:
        """Scene path and transform (4, 4) of every visual object at ``q``.

        With ``scaled`` the columns of the rotation carry the object's mesh
        scale (the static transform); without it the transform is rigid (an
        animation key: meshcat animates position and orientation only).
        """
        pin.forwardKinematics(self.model, self.data, q)
        pin.updateGeometryPlacements(self.model, self.data, self.visual, self.vdata)
        out = []
        for gid, obj in enumerate(self.visual.geometryObjects):
            t = self.vdata.oMg[gid].homogeneous.copy()
            if scaled:
                t[:3, :3] = t[:3, :3] * np.asarray(obj.meshScale)[None, :]
            out.append((f"robot/visuals/{obj.name}", t))
        return out

    def joint_points(self, q: np.ndarray, base: np.ndarray) -> np.ndarray:
        """World positions (J, 3) of the robot's joint origins at ``q`` (for framing)."""
        pin.forwardKinematics(self.model, self.data, q)
        pts = np.array([m.translation for m in self.data.oMi])
        return pts @ base[:3, :3].T + base[:3, 3]

    def animate(
        self,
        vis: Any,
        qs: np.ndarray,
        blend_limit: float = ANIMATION_BLEND_LIMIT,
        pregrasp: np.ndarray | None = None,
        retreat: np.ndarray | None = None,
    ) -> tuple[float, int]:
        """Set the top-k tour (:func:`tour_keys`) on ``vis``; its duration [s] and cuts.

        A tour without a motion (one grasp, no pre-grasp, no retreat) is not set:
        ``(0.0, 0)``.
        """
        tour = tour_keys(qs, pregrasp, retreat, blend_limit)
        if not tour.moves:
            return 0.0, 0
        anim = load_meshcat().animation.Animation(default_framerate=_ANIM_FPS)
        for frame, q in tour.keys:
            with anim.at_frame(vis, frame) as f:
                for path, t in self.placements(q, scaled=False):
                    f[path].set_transform(t)
        vis.set_animation(anim, play=True, repetitions=1)
        return tour.duration_s, tour.cuts


class RobotDrawer(RobotPoser):
    """The visual geometry of a :class:`Robot` under ``/robot/visuals/<name>``.

    Every object of the robot's visual ``GeometryModel`` is drawn (meshes,
    and primitives such as a tool built from boxes), posed by Pinocchio's
    forward kinematics. Meshes are read with trimesh (the scene graph of a
    COLLADA file baked in, as Pinocchio's own geometry loader reads it),
    grouped by material colour and simplified (:func:`_simplified_mesh`), so a
    scene embeds each robot mesh once, small.
    """

    def __init__(self, vis: Any, robot: Robot, base: np.ndarray) -> None:
        super().__init__(robot)
        for obj in self.visual.geometryObjects:
            _draw_geometry(vis[f"robot/visuals/{obj.name}"], obj)
        vis["robot"].set_transform(base)
        self.vis = vis

    def display(self, q: np.ndarray) -> None:
        """Pose the robot's visuals at ``q``."""
        for path, t in self.placements(q):
            self.vis[path].set_transform(t)


@dataclass(frozen=True)
class TourSegment:
    """One grasp of the tour: its index in the tour's solutions and its frames.

    Attributes:
        index: Index of the grasp in the solutions given to :func:`tour_keys`.
        start: First frame (the pre-grasp, else the grasp).
        end: Last frame (the retreat's end, else the end of the hold).
        approach: The approach (pre-grasp to grasp) is shown.
        retreat: The retreat (grasp to retreat's end) is shown.
    """

    index: int
    start: int
    end: int
    approach: bool
    retreat: bool


@dataclass(frozen=True)
class Tour:
    """Keyframes of the top-k tour (:func:`tour_keys`).

    Attributes:
        keys: ``(frame, q)`` in frame order; two keys on one frame are a cut
            (the first ends a motion, the second starts the next one).
        cuts: Number of cuts.
        segments: One per grasp, in tour order.
        moves: Whether anything moves (else there is nothing to animate).
    """

    keys: list[tuple[int, np.ndarray]]
    cuts: int
    segments: list[TourSegment]
    moves: bool

    @property
    def duration_s(self) -> float:
        """Duration of the tour [s]."""
        return (self.keys[-1][0] / _ANIM_FPS) if self.keys else 0.0


def _move_ok(q: np.ndarray, other: np.ndarray | None, blend_limit: float) -> bool:
    return (
        other is not None
        and bool(np.all(np.isfinite(other)))
        and float(np.max(np.abs(other - q), initial=0.0)) <= blend_limit
    )


def _interpolate(
    keys: list[tuple[int, np.ndarray]], frame: int, a: np.ndarray, b: np.ndarray
) -> int:
    """Key the joint-space line a -> b over :data:`_ANIM_MOVE` frames after ``frame``."""
    for s in range(1, _ANIM_MOVE + 1):
        keys.append((frame + s, a + (b - a) * (s / _ANIM_MOVE)))
    return frame + _ANIM_MOVE


def tour_keys(
    qs: np.ndarray,
    pregrasp: np.ndarray | None = None,
    retreat: np.ndarray | None = None,
    blend_limit: float = ANIMATION_BLEND_LIMIT,
) -> Tour:
    """Keyframes of the top-k tour: approach, hold, retreat per grasp; cuts between grasps.

    For each grasp, best first: the pre-grasp held, the joint-space line from
    the pre-grasp to the grasp (the approach), the grasp held, the line from
    the grasp to the retreat's end, that end held; then the tour **cuts** to
    the next grasp's first pose (two keys on one frame: nothing is shown in
    between). After the last grasp it cuts back to the first grasp's
    configuration, the one the static scene shows. It never blends from one
    grasp to another (another IK branch, possibly far away): every pose it
    shows lies on one grasp's checked approach or retreat, interpolated in
    joint space between the configurations the run stored.

    A pre-grasp or retreat configuration that is missing (NaN: no approach
    configured, or none found) is left out: that grasp is held and cut. One
    farther than ``blend_limit`` [rad] from the grasp in some joint (another
    branch: the run's path between them is not a straight joint-space line)
    is shown by a cut instead of a blend.

    Args:
        qs: (k, nq) grasp configurations, best first.
        pregrasp: (k, nq) pre-grasp configurations, or None.
        retreat: (k, nq) configurations at the retreat's end, or None.
        blend_limit: Largest joint jump [rad] (L-infinity) interpolated across.

    Returns:
        The tour (keys, cuts, segments).
    """
    qs = np.asarray(qs, dtype=float).reshape(len(qs), -1) if len(qs) else np.empty((0, 0))
    keys: list[tuple[int, np.ndarray]] = []
    segments: list[TourSegment] = []
    frame = 0
    cuts = 0
    moves = len(qs) > 1
    for i, q in enumerate(qs):
        pre = None if pregrasp is None else np.asarray(pregrasp[i], dtype=float)
        ret = None if retreat is None else np.asarray(retreat[i], dtype=float)
        start = frame
        if i > 0:
            cuts += 1  # the previous grasp's last key sits on this frame too
        show_pre = _move_ok(q, pre, blend_limit)
        show_ret = _move_ok(q, ret, blend_limit)
        if pre is not None and np.all(np.isfinite(pre)) and not show_pre:
            keys += [(frame, pre), (frame + _ANIM_REST, pre)]
            frame += _ANIM_REST
            cuts += 1
        if show_pre:
            assert pre is not None
            keys += [(frame, pre), (frame + _ANIM_REST, pre)]
            frame = _interpolate(keys, frame + _ANIM_REST, pre, q)  # ends on (frame, q)
        else:
            keys.append((frame, q))
        frame += _ANIM_HOLD
        keys.append((frame, q))
        if show_ret:
            assert ret is not None
            frame = _interpolate(keys, frame, q, ret)
            frame += _ANIM_REST
            keys.append((frame, ret))
        moves = moves or show_pre or show_ret
        segments.append(TourSegment(i, start, frame, show_pre, show_ret))
    if moves and len(qs):
        keys.append((frame, qs[0]))  # back to the first grasp: the static scene's pose
        cuts += 1
    return Tour(keys, cuts, segments, moves)


#: Pinocchio joint types the page's forward kinematics knows: kind and axis.
_JOINT_KINDS: dict[str, tuple[str, tuple[float, float, float] | None]] = {
    "JointModelRX": ("revolute", (1.0, 0.0, 0.0)),
    "JointModelRY": ("revolute", (0.0, 1.0, 0.0)),
    "JointModelRZ": ("revolute", (0.0, 0.0, 1.0)),
    "JointModelRevoluteUnaligned": ("revolute", None),
    "JointModelRUBX": ("continuous", (1.0, 0.0, 0.0)),
    "JointModelRUBY": ("continuous", (0.0, 1.0, 0.0)),
    "JointModelRUBZ": ("continuous", (0.0, 0.0, 1.0)),
    "JointModelRevoluteUnboundedUnaligned": ("continuous", None),
    "JointModelPX": ("prismatic", (1.0, 0.0, 0.0)),
    "JointModelPY": ("prismatic", (0.0, 1.0, 0.0)),
    "JointModelPZ": ("prismatic", (0.0, 0.0, 1.0)),
    "JointModelPrismaticUnaligned": ("prismatic", None),
}


def _rows(m: np.ndarray) -> list[float]:
    return [float(v) for v in np.asarray(m, dtype=float).reshape(-1)]


def kinematic_tree(poser: RobotPoser, tool_frame: int | None = None) -> dict[str, Any]:
    """The robot's kinematics for forward kinematics in the page, JSON-ready.

    Joints in Pinocchio's order (parents first): ``parent`` (0: the base),
    ``placement`` (4 x 4 row-major, in the parent joint's frame), ``kind``
    (``revolute``: angle q; ``continuous``: (cos, sin) in two entries of q;
    ``prismatic``: offset q), ``axis`` (unit, joint frame) and ``idx_q``. A
    fixed URDF joint is no joint in Pinocchio: what it carries (a tool) is
    placed on its moving parent. Visual objects: ``path``, ``joint``,
    ``placement`` and ``scale``; the transform of one is
    ``oMi[joint] @ placement`` with its rotation's columns scaled by ``scale``,
    exactly :meth:`RobotPoser.placements`.

    Args:
        poser: The robot's visual poses.
        tool_frame: Id of the grasp frame (its joint and placement are exported), or None.

    Returns:
        ``{"nq", "joints", "visuals", "tool", "unsupported"}``; ``unsupported``
        names joint types the page cannot move (then it does not pose the arm).
    """
    model = poser.model
    joints = []
    unsupported = []
    for j in range(1, model.njoints):
        joint = model.joints[j]
        name = joint.shortname()
        kind, axis = _JOINT_KINDS.get(name, ("", None))
        if not kind:
            unsupported.append(name)
        elif axis is None:
            axis = tuple(float(v) for v in np.asarray(joint.extract().axis, dtype=float))
        joints.append(
            {
                "parent": int(model.parents[j]),
                "placement": _rows(model.jointPlacements[j].homogeneous),
                "kind": kind or name,
                "axis": list(axis) if axis is not None else [0.0, 0.0, 1.0],
                "idx_q": int(joint.idx_q),
            }
        )
    visuals = [
        {
            "path": f"robot/visuals/{obj.name}",
            "joint": int(obj.parentJoint),
            "placement": _rows(obj.placement.homogeneous),
            "scale": [float(v) for v in np.asarray(obj.meshScale, dtype=float)],
        }
        for obj in poser.visual.geometryObjects
    ]
    tool = None
    if tool_frame is not None:
        frame = model.frames[tool_frame]
        tool = {"joint": int(frame.parentJoint), "placement": _rows(frame.placement.homogeneous)}
    return {
        "nq": int(model.nq),
        "joints": joints,
        "visuals": visuals,
        "tool": tool,
        "unsupported": sorted(set(unsupported)),
    }


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
