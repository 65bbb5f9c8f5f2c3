"""Publish stage: a meshcat scene (live or as self-contained HTML) and PNG plots.

The scene holds, under the meshcat root:

=========================== ==================================================
path                        content
=========================== ==================================================
``/robot``                  the robot's visual geometry (every object of its
                            visual model: meshes read by trimesh and simplified,
                            primitives), posed at the top-ranked solution, and
                            an animation stepping through the top-k solutions
                            (blending on one IK branch, cutting across them)
``/object``                 the grasped object (primitive or mesh)
``/environment``            the support table (``environment.table``)
``/grasps/reachable``       one ``LineSegments`` object: a gripper glyph per
                            grasp, coloured by manipulability (viridis)
``/grasps/unreachable``     one ``LineSegments`` object: grey for ``no_ik``,
                            a fixed colour per other ``reason``
``/manifold``               the manifold's triangles (translucent) and edges
=========================== ==================================================

Glyphs are batched: each grasp class is one meshcat object with per-vertex
colours, so the number of meshcat objects does not depend on the number of
grasps N. Above :data:`FULL_GLYPH_LIMIT` grasps the gripper glyph (4 segments)
becomes an approach stick (1 segment) to keep the scene light.

The HTML scene is recorded without a server: a recording window stands in for
meshcat's ZMQ connection, keeps the scene tree exactly as ``meshcat-server``
does, and writes the same static page that ``Visualizer.static_html()`` would
ask the server for. The live viewer (:func:`open_viewer`) starts meshcat's own
server on the loopback interface, or connects to a running one after a
time-bounded probe, so an absent server is a :class:`PublishError`, not a hang.

This is the only module of the package that imports meshcat.
"""

from __future__ import annotations

import base64
import contextlib
import functools
import hashlib
import math
import os
import selectors
import stat
import subprocess
import sys
import time
import warnings
import weakref
from collections.abc import Mapping, Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from gcm_pipeline.errors import InputError, OutputError, PublishError
from gcm_pipeline.geometry.dualquat import dq_to_matrix
from gcm_pipeline.publish.plots import REASON_COLORS, candidate_rows, reason_palette
from gcm_pipeline.rundir.arrays import read_npz
from gcm_pipeline.rundir.transaction import atomic_file
from gcm_pipeline.table import GraspTable

if TYPE_CHECKING:
    from gcm_pipeline.config import Config
    from gcm_pipeline.robot.model import Robot

try:
    import meshcat
    import meshcat.geometry as mg
    import umsgpack
    import zmq
    from meshcat.animation import Animation
    from meshcat.servers.tree import SceneTree, find_node, walk
except ImportError as _exc:  # pragma: no cover - meshcat is a hard dependency
    raise ImportError("gcm_pipeline.publish.scene needs meshcat (pip install meshcat)") from _exc

__all__ = [
    "ANIMATION_BLEND_LIMIT",
    "FULL_GLYPH_LIMIT",
    "REASON_COLORS",
    "SCENE_PATHS",
    "SceneInfo",
    "Viewer",
    "animation_keys",
    "build_scene",
    "legend",
    "open_viewer",
    "probe_server",
    "publish",
    "render_scene_html",
    "stage_counts",
    "write_scene_html",
]

#: Scene paths (relative to the meshcat root) that users can toggle in the controls.
SCENE_PATHS = (
    "/robot",
    "/object",
    "/environment",
    "/grasps/reachable",
    "/grasps/unreachable",
    "/manifold",
)

#: Above this many grasps in one class the gripper glyph becomes an approach stick.
FULL_GLYPH_LIMIT = 20_000

_COLORMAP = "viridis"
_TOP_K_DEFAULT = 10
_ANIM_FPS = 30
_ANIM_HOLD = 15  # frames a solution is held [1/fps s]
_ANIM_MOVE = 9  # frames of joint-space interpolation to the next solution
#: Largest joint jump [rad] (L-infinity) the animation blends across: one IK branch
#: (the default ``continuity.threshold``); beyond it, the animation cuts.
ANIMATION_BLEND_LIMIT = 0.5

# Gripper glyph in the grasp frame (z = approach, fingers along y, origin between
# the fingertips): two fingers, the palm and a stem, as 4 segments [m].
_GLYPH_W, _GLYPH_F, _GLYPH_S = 0.03, 0.03, 0.025
_GRIPPER = np.array(
    [
        [0.0, -_GLYPH_W, 0.0],
        [0.0, -_GLYPH_W, -_GLYPH_F],
        [0.0, _GLYPH_W, 0.0],
        [0.0, _GLYPH_W, -_GLYPH_F],
        [0.0, -_GLYPH_W, -_GLYPH_F],
        [0.0, _GLYPH_W, -_GLYPH_F],
        [0.0, 0.0, -_GLYPH_F],
        [0.0, 0.0, -_GLYPH_F - _GLYPH_S],
    ]
)
_STICK = np.array([[0.0, 0.0, 0.0], [0.0, 0.0, -_GLYPH_F - _GLYPH_S]])

# three.js cameras look along -z with y up; meshcat's camera hangs under
# /Cameras/default/rotated, which rotates y-up into the world's z-up.
_ROT_X90 = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])
_CAMERA_FOV_DEG = 75.0  # meshcat's default camera
_VIEW_DIR = np.array([1.0, 0.75, 0.55])


# -- small results ----------------------------------------------------------------------


@dataclass(frozen=True)
class SceneInfo:
    """What a published scene holds; JSON-ready through :meth:`to_dict`.

    Attributes:
        paths: Top-level scene paths drawn (a subset of :data:`SCENE_PATHS`).
        n_reachable: Number of reachable grasps drawn.
        n_unreachable: Number of unreachable grasps drawn.
        glyph: ``"gripper"`` (4 segments per grasp) or ``"stick"`` (1 segment).
        meshcat_objects: Number of ``set_object`` commands sent (independent of N
            for a given robot, object and environment).
        legend: Colour legend (see :func:`legend`).
        camera: ``{"position": [x, y, z], "target": [x, y, z]}`` in the world [m].
        top_k: Number of solutions in the robot animation.
        animation_s: Duration of the robot animation [s].
        animation_cuts: Steps of the animation that cut to the next solution
            (another IK branch) instead of blending to it.
    """

    paths: tuple[str, ...]
    n_reachable: int
    n_unreachable: int
    glyph: str
    meshcat_objects: int
    legend: dict[str, Any]
    camera: dict[str, list[float]]
    top_k: int
    animation_s: float
    animation_cuts: int = 0

    def to_dict(self) -> dict[str, Any]:
        """Return the info as plain JSON-ready data."""
        return asdict(self)


# -- colours ----------------------------------------------------------------------------


def _hex(rgb: Sequence[float]) -> str:
    return "#" + "".join(f"{int(round(255 * float(c))):02x}" for c in rgb[:3])


def _manipulability_range(values: np.ndarray) -> tuple[float, float]:
    finite = values[np.isfinite(values)]
    if finite.size == 0:
        return 0.0, 1.0
    lo, hi = float(finite.min()), float(finite.max())
    if hi <= lo:
        hi = lo + max(abs(lo), 1.0) * 1e-9
    return lo, hi


def _column(grasps: GraspTable, name: str, default: Any) -> np.ndarray:
    col = grasps.get(name)
    if col is None:
        return np.full(len(grasps), default)
    return np.asarray(col)


def _classes(grasps: GraspTable) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Reachable mask, reasons (str) and manipulability (float) of every row."""
    n = len(grasps)
    reachable = _column(grasps, "reachable", False).astype(bool)
    reason = _column(grasps, "reason", "").astype(str)
    if "manipulability" in grasps:
        manip = np.asarray(grasps["manipulability"], dtype=float)
    else:
        manip = np.full(n, np.nan)
    if "reachable" not in grasps:
        reason = np.where(reason == "", "unchecked", reason)
    reason = np.where(~reachable & (reason == ""), "no_ik", reason)
    return reachable, reason, manip


def legend(grasps: GraspTable) -> dict[str, Any]:
    """Colour legend of the grasp glyphs, JSON-ready (for the run summary).

    Args:
        grasps: The grasp table (``reachable``, ``reason``, ``manipulability``
            are used when present).

    Returns:
        ``{"colormap": "viridis", "metric_range": [vmin, vmax],
        "ticks": [5 values], "tick_colors": [5 hex colours],
        "reachable": n, "unreachable": {reason: {"color": hex, "count": n}}}``.
        ``metric_range`` is the manipulability range over the reachable grasps
        that the colormap spans (``[0, 1]`` when there is none).
    """
    reachable, reason, manip = _classes(grasps)
    vmin, vmax = _manipulability_range(manip[reachable])
    ticks = np.linspace(vmin, vmax, 5)
    cmap = _cmap()
    unreach = reason[~reachable]
    names, counts = np.unique(unreach, return_counts=True)
    palette = reason_palette(list(names))
    return {
        "colormap": _COLORMAP,
        "metric_range": [vmin, vmax],
        "ticks": [float(t) for t in ticks],
        "tick_colors": [_hex(c) for c in cmap(np.linspace(0.0, 1.0, 5))],
        "reachable": int(reachable.sum()),
        "unreachable": {
            str(r): {"color": _hex(palette[str(r)]), "count": int(c)}
            for r, c in zip(names, counts, strict=True)
        },
    }


def _cmap() -> Any:
    from matplotlib import colormaps

    return colormaps[_COLORMAP]


# -- geometry ---------------------------------------------------------------------------


def _poses(grasps: GraspTable) -> tuple[np.ndarray, np.ndarray]:
    """Rotations (N, 3, 3) and positions (N, 3) of the grasp frames in the world."""
    m = dq_to_matrix(np.asarray(grasps["dq"], dtype=float))
    return m[:, :3, :3], m[:, :3, 3]


def _glyph_segments(rot: np.ndarray, trans: np.ndarray, template: np.ndarray) -> np.ndarray:
    """World vertices (N * V, 3) float32 of a glyph template (V, 3) at N poses."""
    pts = np.einsum("nij,vj->nvi", rot.astype(np.float32), template.astype(np.float32))
    pts += trans.astype(np.float32)[:, None, :]
    return pts.reshape(-1, 3)


def _line_segments(vertices: np.ndarray, colors: np.ndarray, linewidth: float = 1.0) -> Any:
    geometry = mg.PointsGeometry(
        np.ascontiguousarray(vertices.T, dtype=np.float32),
        np.ascontiguousarray(colors.T, dtype=np.float32),
    )
    material = mg.LineBasicMaterial(vertexColors=True, linewidth=linewidth)
    return mg.LineSegments(geometry, material)


def _translation(xyz: Sequence[float]) -> np.ndarray:
    m = np.eye(4)
    m[:3, 3] = xyz
    return m


# -- scene parts ------------------------------------------------------------------------


def _draw_grasps(
    vis: Any, grasps: GraspTable, rot: np.ndarray, trans: np.ndarray
) -> tuple[list[str], str, int, int]:
    reachable, reason, manip = _classes(grasps)
    paths: list[str] = []
    n_r, n_u = int(reachable.sum()), int((~reachable).sum())
    template = _GRIPPER if max(n_r, n_u) <= FULL_GLYPH_LIMIT else _STICK
    glyph = "gripper" if template is _GRIPPER else "stick"
    nv = len(template)
    if n_r:
        vmin, vmax = _manipulability_range(manip[reachable])
        m = manip[reachable]
        t = np.clip((np.where(np.isfinite(m), m, vmin) - vmin) / (vmax - vmin), 0.0, 1.0)
        rgb = _cmap()(t)[:, :3].astype(np.float32)
        verts = _glyph_segments(rot[reachable], trans[reachable], template)
        colors = np.repeat(rgb, nv, axis=0)
        vis["grasps/reachable"].set_object(_line_segments(verts, colors, 2.0))
        paths.append("/grasps/reachable")
    if n_u:
        unreach = reason[~reachable]
        palette = reason_palette(list(np.unique(unreach)))
        names = list(palette)
        table = np.array([palette[n] for n in names], dtype=np.float32)
        idx = np.searchsorted(np.array(names), unreach)
        verts = _glyph_segments(rot[~reachable], trans[~reachable], template)
        colors = np.repeat(table[idx], nv, axis=0)
        vis["grasps/unreachable"].set_object(_line_segments(verts, colors, 1.0))
        paths.append("/grasps/unreachable")
    return paths, glyph, n_r, n_u


def _object_geometry(obj: Any) -> tuple[Any, np.ndarray]:
    """Meshcat geometry of the config's object and its transform in the object frame."""
    shape = obj.shape
    dims = obj.dims
    if shape == "cylinder":
        # meshcat cylinders run along y, centred: stand it on its base along z
        local = _translation((0.0, 0.0, dims.height / 2.0))
        local[:3, :3] = _ROT_X90
        return mg.Cylinder(dims.height, dims.radius), local
    if shape == "box":
        return mg.Box(list(dims.size)), np.eye(4)
    if shape == "sphere":
        return mg.Sphere(dims.radius), np.eye(4)
    if shape == "plane":
        # a thin box centred on the frame, as the collision world models it
        sx, sy = dims.size
        return mg.Box([sx, sy, 0.002]), np.eye(4)
    # mesh
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
    return loaders[ext](str(path)), local


def _object_points(obj: Any) -> np.ndarray:
    """A few world points (K, 3) spanning the object (for framing the camera)."""
    dims = obj.dims
    if obj.shape == "cylinder":
        r, h = dims.radius, dims.height
        local = np.array([[-r, -r, 0.0], [r, r, h]])
    elif obj.shape in ("box", "plane"):
        size = np.zeros(3)
        size[: len(dims.size)] = dims.size
        local = np.array([-size / 2, size / 2])
    elif obj.shape == "sphere":
        local = np.array([[-dims.radius] * 3, [dims.radius] * 3])
    else:
        local = np.zeros((1, 3))
    m = obj.pose.matrix()
    return local @ m[:3, :3].T + m[:3, 3]


def _draw_object(vis: Any, obj: Any) -> list[str]:
    geometry, local = _object_geometry(obj)
    material = mg.MeshPhongMaterial(color=0xD9A441, opacity=0.7, transparent=True)
    vis["object"].set_transform(obj.pose.matrix())
    vis["object/shape"].set_object(geometry, material)
    vis["object/shape"].set_transform(local)
    return ["/object"]


def _draw_environment(vis: Any, config: Config) -> list[str]:
    env = config.environment
    paths: list[str] = []
    if env.table is not None:
        sx, sy, sz = env.table.size
        cx, cy = env.table.center_xy
        material = mg.MeshLambertMaterial(color=0xC8C3BA)
        vis["environment/table"].set_object(mg.Box([sx, sy, sz]), material)
        vis["environment/table"].set_transform(_translation((cx, cy, env.table.height - sz / 2)))
        # the table replaces meshcat's grid, which would z-fight with its top
        vis["/Grid"].set_property("visible", False)
        vis["/Axes"].set_property("visible", False)
        paths.append("/environment")
    for i, obs in enumerate(env.obstacles):
        if obs.shape == "mesh" and (obs.mesh is None or not Path(obs.mesh).is_file()):
            warnings.warn(f"obstacle {i}: mesh {obs.mesh} not found; not drawn", stacklevel=3)
            continue
        geometry, local = _object_geometry(obs)
        name = obs.name or f"obstacle_{i}"
        material = mg.MeshLambertMaterial(color=0x8C8C99, opacity=0.7, transparent=True)
        vis[f"environment/{name}"].set_transform(obs.pose.matrix())
        vis[f"environment/{name}/shape"].set_object(geometry, material)
        vis[f"environment/{name}/shape"].set_transform(local)
        if "/environment" not in paths:
            paths.append("/environment")
    return paths


def _draw_manifold(vis: Any, grasps: GraspTable, manifold: Any, trans: np.ndarray) -> list[str]:
    if manifold is None:
        return []
    tris = np.asarray(getattr(manifold, "triangles", np.empty((0, 3))), dtype=np.int64)
    if tris.size == 0:
        return []
    chart = getattr(manifold, "chart", None)
    n_chart = len(chart) if chart is not None else int(tris.max()) + 1
    rows = candidate_rows(grasps, n_chart)
    if tris.max() >= len(rows):
        warnings.warn(
            f"manifold triangles use vertex {int(tris.max())} but the table has "
            f"{len(rows)} candidate rows; manifold not drawn",
            stacklevel=3,
        )
        return []
    verts = trans[rows].astype(np.float32)
    material = mg.MeshLambertMaterial(
        color=0x4A90D9, opacity=0.28, transparent=True, depthWrite=False
    )
    vis["manifold/triangles"].set_object(mg.TriangularMeshGeometry(verts, tris), material)
    edges = np.concatenate([tris[:, [0, 1]], tris[:, [1, 2]], tris[:, [2, 0]]])
    edges = np.unique(np.sort(edges, axis=1), axis=0)
    seg = verts[edges.reshape(-1)]
    colors = np.tile(np.array([[0.16, 0.35, 0.62]], dtype=np.float32), (len(seg), 1))
    vis["manifold/edges"].set_object(_line_segments(seg, colors, 1.0))
    return ["/manifold"]


def _top_solutions(grasps: GraspTable, k: int) -> np.ndarray:
    """Configurations (<= k, nq) of the best-ranked reachable grasps, best first."""
    if "q" not in grasps:
        return np.empty((0, 0))
    q = np.asarray(grasps["q"], dtype=float)
    if "rank" in grasps:
        rank = np.asarray(grasps["rank"], dtype=np.int64)
        order = np.flatnonzero(rank > 0)
        order = order[np.argsort(rank[order], kind="stable")]
    else:
        order = np.flatnonzero(_column(grasps, "reachable", False).astype(bool))
    order = order[np.all(np.isfinite(q[order]), axis=1)] if len(order) else order
    return q[order[:k]]


class _RobotDrawer:
    """The visual geometry of a :class:`Robot` under ``/robot/visuals/<name>``.

    Every object of the robot's visual ``GeometryModel`` is drawn (meshes,
    and primitives such as a tool built from boxes), posed by Pinocchio's
    forward kinematics. Meshes are read with trimesh (the scene graph of a
    COLLADA file baked in, as Pinocchio's own geometry loader reads it),
    grouped by material colour and simplified (:func:`_simplified_mesh`), so a
    scene embeds each robot mesh once, small.
    """

    def __init__(self, vis: Any, robot: Robot, base: np.ndarray) -> None:
        import pinocchio as pin

        self.pin = pin
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
        for path, t in self.placements(q):
            self.vis[path].set_transform(t)

    def placements(self, q: np.ndarray) -> list[tuple[str, np.ndarray]]:
        pin = self.pin
        pin.forwardKinematics(self.model, self.data, q)
        pin.updateGeometryPlacements(self.model, self.data, self.visual, self.vdata)
        out = []
        for gid, obj in enumerate(self.visual.geometryObjects):
            t = self.vdata.oMg[gid].homogeneous.copy()
            t[:3, :3] = t[:3, :3] * np.asarray(obj.meshScale)[None, :]
            out.append((f"robot/visuals/{obj.name}", t))
        return out

    def animate(
        self, vis: Any, qs: np.ndarray, blend_limit: float = ANIMATION_BLEND_LIMIT
    ) -> tuple[float, int]:
        """Set the top-k animation (:func:`animation_keys`); its duration [s] and cuts."""
        anim = Animation(default_framerate=_ANIM_FPS)
        keys, cuts = animation_keys(qs, blend_limit)
        for frame, q in keys:
            self._keyframe(anim, vis, frame, q)
        vis.set_animation(anim, play=True, repetitions=1)
        return (keys[-1][0] + 1) / _ANIM_FPS, cuts

    def _keyframe(self, anim: Animation, vis: Any, frame: int, q: np.ndarray) -> None:
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


class _PackedMesh(mg.Geometry):
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
    return [(color, _PackedMesh(verts, faces)) for color, verts, faces in groups]


_MeshGroups = list[tuple[int, np.ndarray, np.ndarray]]


@functools.cache
def _simplifier_versions() -> str:
    """Versions of the libraries behind :func:`_simplify_mesh`, for the cache key."""
    from importlib.metadata import PackageNotFoundError, version

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
    import coal

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
        local[:3, :3] = _ROT_X90  # meshcat cylinders run along y, coal's along z
        node["0"].set_transform(local)
    elif obj.meshPath and Path(obj.meshPath).is_file():
        for k, (c, mesh) in enumerate(_simplified_mesh(obj.meshPath)):
            node[str(k)].set_object(mesh, material(color if color is not None else c))
    elif hasattr(geom, "num_tris") and geom.num_tris > 0:  # a mesh built in memory
        verts = np.array([geom.vertices(i) for i in range(geom.num_vertices)])
        tris = np.array([list(geom.tri_indices(i)) for i in range(geom.num_tris)])
        node["0"].set_object(_PackedMesh(verts, tris), material(default))
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


def _robot_points(drawer: _RobotDrawer, q: np.ndarray, base: np.ndarray) -> np.ndarray:
    """World positions (J, 3) of the robot's joint origins at ``q`` (for framing)."""
    pin = drawer.pin
    pin.forwardKinematics(drawer.model, drawer.data, q)
    pts = np.array([m.translation for m in drawer.data.oMi])
    return pts @ base[:3, :3].T + base[:3, 3]


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


def _set_camera(vis: Any, position: np.ndarray) -> None:
    """Place meshcat's default camera at ``position`` (world, [m]).

    The camera hangs under ``/Cameras/default/rotated``, whose rotation undoes
    the viewer's z-up to y-up turn of the scene, so the camera's local
    coordinates are three.js world coordinates: ``R_x(90 deg)^T @ world``.
    meshcat 0.3 has no command for the orbit target (the static page sets
    ``viewer.controls.target``, see :func:`_orbit_js`); without it the camera
    looks at the world origin.
    """
    vis["/Cameras/default"].set_transform(np.eye(4))
    local = _ROT_X90.T @ np.asarray(position, dtype=float)
    vis["/Cameras/default/rotated/<object>"].set_property("position", local.tolist())


def build_scene(
    vis: Any,
    grasps: GraspTable,
    manifold: Any,
    robot: Robot | None,
    config: Config,
    *,
    orbit_target: bool = False,
) -> SceneInfo:
    """Draw the whole scene into a meshcat visualizer.

    Args:
        vis: A ``meshcat.Visualizer`` (live or recording).
        grasps: The grasp table (``dq`` required; ``reachable``, ``reason``,
            ``manipulability``, ``q``, ``rank``, ``origin`` used when present).
        manifold: The manifold (``triangles`` (T, 3) candidate ids, ``chart``
            (Nc, 2)) or None.
        robot: The robot, or None to leave it out.
        config: The run config (``object``, ``environment``, ``robot.base_pose``,
            ``ranking.top_k``).
        orbit_target: The page sets the orbit controls' target (static HTML).

    Returns:
        What was drawn, with the colour legend and the camera.
    """
    n = len(grasps)
    if n and "dq" not in grasps:
        raise PublishError("grasp table has no 'dq' column; nothing to draw")
    rot, trans = _poses(grasps) if n else (np.empty((0, 3, 3)), np.empty((0, 3)))
    vis.delete()
    paths: list[str] = []
    frame_pts: list[np.ndarray] = []
    base = config.robot.base_pose.matrix()
    top_k = int(getattr(config.ranking, "top_k", _TOP_K_DEFAULT))
    anim_s = 0.0
    cuts = 0
    n_top = 0
    robot_pts = np.zeros((0, 3))
    if robot is not None:
        drawer = _RobotDrawer(vis, robot, base)
        qs = _top_solutions(grasps, top_k)
        home = np.asarray(getattr(robot, "home", np.zeros(robot.nq)), dtype=float)
        q0 = qs[0] if len(qs) else home
        drawer.display(q0)
        robot_pts = _robot_points(drawer, q0, base)
        frame_pts.append(robot_pts)
        if len(qs) > 1:
            blend = float(getattr(getattr(config, "continuity", None), "threshold", 0.5))
            anim_s, cuts = drawer.animate(vis, qs, blend)
        n_top = len(qs)
        paths.append("/robot")
    if config.object is not None:
        paths += _draw_object(vis, config.object)
        frame_pts.append(_object_points(config.object))
    paths += _draw_environment(vis, config)
    gpaths, glyph, n_r, n_u = _draw_grasps(vis, grasps, rot, trans) if n else ([], "none", 0, 0)
    paths += gpaths
    paths += _draw_manifold(vis, grasps, manifold, trans)
    others = np.concatenate(frame_pts) if frame_pts else np.zeros((1, 3))
    target, position = _camera(trans, others, robot_pts)
    if not orbit_target:
        # live viewer: the camera looks at the world origin; keep the view direction
        # and back off until the scene fits
        radius = float(np.max(np.linalg.norm(others - 0.0, axis=1), initial=0.2))
        radius = max(radius, float(np.linalg.norm(target)) + 0.2)
        direction = (position - target) / np.linalg.norm(position - target)
        target = np.zeros(3)
        position = direction * radius / math.sin(math.radians(_CAMERA_FOV_DEG) / 2.0)
    _set_camera(vis, position)
    window = vis.window
    n_objects = int(getattr(window, "n_objects", -1))
    return SceneInfo(
        paths=tuple(paths),
        n_reachable=n_r,
        n_unreachable=n_u,
        glyph=glyph,
        meshcat_objects=n_objects,
        legend=legend(grasps),
        camera={"position": position.tolist(), "target": target.tolist()},
        top_k=n_top,
        animation_s=anim_s,
        animation_cuts=cuts,
    )


# -- recording window and static HTML ---------------------------------------------------


class _RecordingWindow:
    """Stands in for meshcat's ZMQ window: keeps the scene tree like ``meshcat-server``.

    ``meshcat.Visualizer(window=_RecordingWindow())`` draws without a server;
    :meth:`static_html` then builds the page that the server's ``get_scene``
    would return (same tree walk, same command encoding).
    """

    def __init__(self) -> None:
        self.tree = SceneTree()
        self.web_url = ""
        self.zmq_url = ""
        self.n_objects = 0

    def send(self, command: Any) -> None:
        data = command.lower()
        kind = data["type"]
        path = [p for p in data["path"].split("/") if p]
        packed = umsgpack.packb(data)
        node = find_node(self.tree, path)
        if kind == "set_object":
            node.object = packed
            node.properties = []
            self.n_objects += 1
        elif kind == "set_transform":
            node.transform = packed
        elif kind == "set_property":
            node.properties.append(packed)
        elif kind == "set_animation":
            node.animation = packed
        elif kind == "delete":
            if path:
                parent = find_node(self.tree, path[:-1])
                parent.pop(path[-1], None)
            else:
                self.tree = SceneTree()
        else:  # pragma: no cover - meshcat sends only the above
            raise PublishError(f"unsupported meshcat command {kind!r}")

    def get_image(self) -> None:  # pragma: no cover - no browser behind it
        raise PublishError("a recorded scene has no browser to capture an image from")

    def commands(self) -> list[bytes]:
        """The msgpack-encoded commands in the order the server would replay them."""
        out: list[bytes] = []
        for node in walk(self.tree):
            if node.object is not None:
                out.append(node.object)
            out.extend(node.properties)
            if node.transform is not None:
                out.append(node.transform)
            if node.animation is not None:
                out.append(node.animation)
        return out

    def static_html(self, extra_js: str = "", title: str = "gcm_pipeline scene") -> str:
        """The self-contained page: meshcat's viewer script and the recorded commands."""
        js_path = Path(meshcat.__file__).parent / "viewer" / "dist" / "main.min.js"
        viewer_js = js_path.read_text(encoding="utf-8")
        parts = []
        for blob in self.commands():
            b64 = base64.b64encode(blob).decode("ascii")
            parts.append(
                f'fetch("data:application/octet-binary;base64,{b64}")\n'
                "    .then(res => res.arrayBuffer())\n"
                "    .then(buffer => viewer.handle_command_bytearray(new Uint8Array(buffer)));\n"
            )
        return _HTML.format(
            title=title, mainminjs=viewer_js, commands="".join(parts), extra=extra_js
        )


_HTML = """<!DOCTYPE html>
<html>
    <head> <meta charset=utf-8> <title>{title}</title> </head>
    <body>
        <div id="meshcat-pane">
        </div>
        <script>
{mainminjs}
        </script>
        <script>
            var viewer = new MeshCat.Viewer(document.getElementById("meshcat-pane"));
{commands}
{extra}
        </script>
        <style>
            body {{margin: 0; }}
            #meshcat-pane {{
                width: 100vw;
                height: 100vh;
                overflow: hidden;
            }}
        </style>
        <script id="embedded-json"></script>
    </body>
</html>
"""


def _orbit_js(target: Sequence[float]) -> str:
    """Script that turns the page's orbit controls about ``target`` (world, [m])."""
    x, y, z = (float(v) for v in _ROT_X90.T @ np.asarray(target, dtype=float))
    return (
        f"viewer.controls.target.set({x!r}, {y!r}, {z!r});\n"
        "viewer.controls.update();\nviewer.set_dirty();\n"
    )


def render_scene_html(
    grasps: GraspTable, manifold: Any, robot: Robot | None, config: Config
) -> tuple[str, SceneInfo]:
    """Build the scene without a server and return the self-contained HTML page.

    Args:
        grasps: The grasp table.
        manifold: The manifold or None.
        robot: The robot or None.
        config: The run config.

    Returns:
        The page (opens from disk, no server) and what it holds.
    """
    window = _RecordingWindow()
    vis = meshcat.Visualizer(window=window)
    info = build_scene(vis, grasps, manifold, robot, config, orbit_target=True)
    return window.static_html(extra_js=_orbit_js(info.camera["target"])), info


def write_scene_html(
    path: str | os.PathLike[str],
    grasps: GraspTable,
    manifold: Any,
    robot: Robot | None,
    config: Config,
) -> SceneInfo:
    """Write the self-contained HTML scene to ``path`` (see :func:`render_scene_html`)."""
    html, info = render_scene_html(grasps, manifold, robot, config)
    path = Path(path)
    try:
        path.write_text(html, encoding="utf-8")
    except OSError as exc:
        raise PublishError(f"cannot write scene {str(path)!r}: {exc}") from exc
    return info


# -- counts and publish -----------------------------------------------------------------


def stage_counts(grasps: GraspTable, manifold: Any) -> dict[str, int]:
    """Per-stage counts in the summary's keys, derived from the table and manifold.

    Returns:
        ``{"candidates", "triangles", "triangles_dropped", "densified", "reachable"}``.
    """
    origin = grasps.get("origin")
    n = len(grasps)
    candidates = n if origin is None else int((np.asarray(origin).astype(str) == "candidate").sum())
    tris = getattr(manifold, "triangles", None)
    dropped = getattr(manifold, "dropped", None)
    return {
        "candidates": candidates,
        "triangles": 0 if tris is None else len(tris),
        "triangles_dropped": 0 if dropped is None else len(dropped),
        "densified": n,
        "reachable": int(_column(grasps, "reachable", False).astype(bool).sum()),
    }


def publish(
    grasps: GraspTable,
    manifold: Any,
    robot: Robot | None,
    config: Config,
    out_dir: str | os.PathLike[str],
    counts: Mapping[str, int] | None = None,
) -> list[Path]:
    """Write the files ``config.publish`` asks for into ``out_dir``.

    ``scene.html`` (when ``publish.html``) and ``manifold.png``,
    ``manipulability_hist.png``, ``counts.png`` (when ``publish.plots``). The
    live viewer is separate (:func:`open_viewer`), called once the run
    directory is complete.

    Args:
        grasps: The grasp table.
        manifold: The manifold or None.
        robot: The robot or None.
        config: The run config.
        out_dir: An existing directory.
        counts: Per-stage counts for the bar chart (default: :func:`stage_counts`).

    Returns:
        The paths written, in that order.

    Raises:
        PublishError: A file cannot be written.
    """
    out = Path(out_dir)
    written: list[Path] = []
    if config.publish.html:
        path = out / "scene.html"
        write_scene_html(path, grasps, manifold, robot, config)
        written.append(path)
    if config.publish.plots:
        from gcm_pipeline.publish.plots import write_plots

        written += write_plots(grasps, manifold, counts or stage_counts(grasps, manifold), out)
    return written


# -- live viewer ------------------------------------------------------------------------

# Runs meshcat's server with the web server bound to the loopback interface
# (meshcat's own launcher listens on all interfaces for HTTP).
_SERVER_CODE = """
import os, sys, threading, time
import tornado.web
from meshcat.servers import zmqserver as z

_parent = int(sys.argv[1])
_detached = sys.argv[2:] == ["detach"]

def _watch_parent():
    # exit with the process that started us, even if it could not stop us
    while True:
        time.sleep(1.0)
        if os.getppid() != _parent:
            os._exit(0)

if not _detached:  # a detached server outlives its starter (stop it by its pid)
    threading.Thread(target=_watch_parent, daemon=True).start()

class _App(tornado.web.Application):
    def listen(self, port, address="127.0.0.1", **kwargs):
        return super().listen(port, address="127.0.0.1", **kwargs)

class _Bridge(z.ZMQWebSocketBridge):
    def make_app(self):
        return _App([
            (r"/static/(.*)", z.StaticFileHandlerNoCache,
             {"path": z.VIEWER_ROOT, "default_filename": z.VIEWER_HTML}),
            (r"/", z.WebSocketHandler, {"bridge": self}),
        ])

bridge = _Bridge(host="127.0.0.1")
print("zmq_url=" + bridge.zmq_url, flush=True)
print("web_url=" + bridge.web_url, flush=True)
sys.stdout = open(os.devnull, "w")
try:
    bridge.run()
except KeyboardInterrupt:
    pass
"""


def _request(sock: Any, frames: list[bytes], what: str, url: str, timeout_s: float) -> bytes:
    try:
        sock.send_multipart(frames)
        return bytes(sock.recv())
    except zmq.Again:
        raise PublishError(
            f"meshcat server at {url} did not answer {what!r} within {timeout_s:g} s "
            "(is `meshcat-server` running there? start one or set publish.zmq_url: null)"
        ) from None
    except zmq.ZMQError as exc:
        raise PublishError(f"meshcat server at {url}: {exc}") from exc


def _req_socket(url: str, timeout_s: float) -> Any:
    sock: Any = zmq.Context.instance().socket(zmq.REQ)
    sock.setsockopt(zmq.LINGER, 0)
    sock.setsockopt(zmq.RCVTIMEO, max(1, int(timeout_s * 1000)))
    sock.setsockopt(zmq.SNDTIMEO, max(1, int(timeout_s * 1000)))
    try:
        sock.connect(url)
    except zmq.ZMQError as exc:
        sock.close(0)
        raise PublishError(
            f"invalid meshcat zmq_url {url!r}: {exc} (expected e.g. tcp://127.0.0.1:6000)"
        ) from exc
    return sock


def probe_server(zmq_url: str, timeout_s: float) -> str:
    """Ask a meshcat server for its web URL, giving up after ``timeout_s``.

    Args:
        zmq_url: The server's ZMQ address, e.g. ``tcp://127.0.0.1:6000``.
        timeout_s: Time bound [s].

    Returns:
        The server's web URL.

    Raises:
        PublishError: No answer within the time bound (names the URL) or a bad URL.
    """
    sock = _req_socket(zmq_url, timeout_s)
    try:
        return _request(sock, [b"url"], "url", zmq_url, timeout_s).decode("utf-8")
    finally:
        sock.close(0)


class _ZmqWindow:
    """meshcat's ZMQ window with time-bounded requests (a dead server raises, never hangs)."""

    def __init__(self, zmq_url: str, web_url: str, timeout_s: float) -> None:
        self.zmq_url = zmq_url
        self.web_url = web_url
        self.timeout_s = timeout_s
        self.n_objects = 0
        self._sock = _req_socket(zmq_url, timeout_s)

    def send(self, command: Any) -> None:
        data = command.lower()
        if data["type"] == "set_object":
            self.n_objects += 1
        frames = [
            data["type"].encode("utf-8"),
            data["path"].encode("utf-8"),
            umsgpack.packb(data),
        ]
        _request(self._sock, frames, data["type"], self.zmq_url, self.timeout_s)

    def get_scene(self) -> str:
        return _request(
            self._sock, [b"get_scene"], "get_scene", self.zmq_url, self.timeout_s
        ).decode("utf-8")

    def close(self) -> None:
        self._sock.close(0)


def _start_server(
    timeout_s: float, detach: bool = False
) -> tuple[subprocess.Popen[bytes], str, str]:
    """Start meshcat's server on 127.0.0.1; return (process, zmq_url, web_url).

    A ``detach``-ed server keeps running after this process exits.
    """
    extra = ["detach"] if detach else []
    proc = subprocess.Popen(
        [sys.executable, "-u", "-c", _SERVER_CODE, str(os.getpid()), *extra],
        stdout=subprocess.PIPE,
        stderr=subprocess.DEVNULL,
        stdin=subprocess.DEVNULL,
        start_new_session=True,
    )
    assert proc.stdout is not None
    urls: dict[str, str] = {}
    deadline = time.monotonic() + timeout_s
    buf = b""
    with selectors.DefaultSelector() as sel:
        sel.register(proc.stdout, selectors.EVENT_READ)
        while len(urls) < 2:
            left = deadline - time.monotonic()
            if left <= 0 or proc.poll() is not None:
                _stop(proc)
                why = "exited" if proc.poll() is not None else f"gave no URL in {timeout_s:g} s"
                raise PublishError(f"meshcat server on 127.0.0.1 {why}")
            if not sel.select(left):
                continue
            chunk = os.read(proc.stdout.fileno(), 4096)
            if not chunk:
                continue
            buf += chunk
            *lines, buf = buf.split(b"\n")
            for line in lines:
                key, _, value = line.decode("utf-8", "replace").strip().partition("=")
                if key in ("zmq_url", "web_url"):
                    urls[key] = value
    return proc, urls["zmq_url"], urls["web_url"]


def _stop(proc: subprocess.Popen[bytes] | None) -> None:
    if proc is None or proc.poll() is not None:
        if proc is not None and proc.stdout is not None:
            proc.stdout.close()
        return
    proc.terminate()
    try:
        proc.wait(timeout=5)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.wait()
    if proc.stdout is not None:
        proc.stdout.close()


@dataclass
class Viewer:
    """A live meshcat scene.

    Attributes:
        url: Web address to open in a browser.
        zmq_url: The server's ZMQ address.
        info: What the scene holds.
        visualizer: The ``meshcat.Visualizer`` (draw more with it if you like).
        owns_server: Whether :meth:`close` stops the server (started by
            :func:`open_viewer`).
        server_pid: Process id of the server started by :func:`open_viewer`
            (None for a server at ``publish.zmq_url``); a detached server
            keeps running after :meth:`close` until this process is stopped.
    """

    url: str
    zmq_url: str
    info: SceneInfo
    visualizer: Any = field(repr=False)
    owns_server: bool = False
    server_pid: int | None = None
    closed: bool = False
    _proc: subprocess.Popen[bytes] | None = field(default=None, repr=False)
    _finalizer: Any = field(default=None, repr=False)

    def close(self) -> None:
        """Disconnect, and stop the server if this viewer started it. Idempotent."""
        window = getattr(self.visualizer, "window", None)
        if isinstance(window, _ZmqWindow):
            window.close()
        if self._finalizer is not None:
            self._finalizer()
        self.closed = True

    def __enter__(self) -> Viewer:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def open_viewer(
    grasps: GraspTable,
    manifold: Any,
    robot: Robot | None,
    config: Config,
    *,
    detach: bool = False,
) -> Viewer:
    """Publish the scene to a live meshcat server.

    With ``config.publish.zmq_url`` None, meshcat's server is started on
    127.0.0.1 (ZMQ and HTTP) and stopped by :meth:`Viewer.close` (unless
    ``detach``: then it keeps serving the scene after this process exits,
    until its ``server_pid`` is stopped); otherwise the server at ``zmq_url``
    is probed within ``publish.connect_timeout_s`` and used.

    Args:
        grasps: The grasp table.
        manifold: The manifold or None.
        robot: The robot or None.
        config: The run config.
        detach: Leave a server started here running after :meth:`Viewer.close`.

    Returns:
        The viewer; open ``viewer.url`` in a browser, call ``viewer.close()`` when done.

    Raises:
        PublishError: The server is unreachable within the time bound (names the
            URL), cannot start, or stops answering.
    """
    timeout = float(config.publish.connect_timeout_s)
    proc = None
    if config.publish.zmq_url is None:
        proc, zmq_url, web_url = _start_server(max(timeout, 20.0), detach=detach)
    else:
        zmq_url = config.publish.zmq_url
        web_url = probe_server(zmq_url, timeout)
    window = None
    try:
        # large scenes take a while to forward: allow more than the connect bound
        window = _ZmqWindow(zmq_url, web_url, max(timeout, 60.0))
        vis = meshcat.Visualizer(window=window)
        info = build_scene(vis, grasps, manifold, robot, config)
    except BaseException:
        if window is not None:
            window.close()
        _stop(proc)
        raise
    viewer = Viewer(
        url=web_url,
        zmq_url=zmq_url,
        info=info,
        visualizer=vis,
        owns_server=proc is not None and not detach,
        server_pid=None if proc is None else proc.pid,
        _proc=proc,
    )
    if detach:
        if proc is not None and proc.stdout is not None:
            proc.stdout.close()
        return viewer
    # stops the server on close(), when the viewer is garbage-collected, or at exit
    viewer._finalizer = weakref.finalize(viewer, _stop, proc)
    return viewer
