"""The published scene: what a run's meshcat scene holds and how it is drawn.

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

The same scene is recorded into a self-contained page
(:mod:`gcm_pipeline.outputs.html`) or sent to a live meshcat server
(:mod:`gcm_pipeline.outputs.live`); the robot's part is drawn by
:mod:`gcm_pipeline.outputs.robot_view`.
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Sequence
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import meshcat.geometry as mg
import numpy as np

from gcm_pipeline.errors import PublishError
from gcm_pipeline.geometry.dualquat import dq_to_matrix
from gcm_pipeline.outputs.plots import candidate_rows, reason_palette
from gcm_pipeline.outputs.robot_view import ROT_X90, RobotDrawer
from gcm_pipeline.table import GraspTable

if TYPE_CHECKING:
    from gcm_pipeline.config import Config
    from gcm_pipeline.robot.model import Robot

__all__ = [
    "FULL_GLYPH_LIMIT",
    "SCENE_PATHS",
    "SceneInfo",
    "build_scene",
    "legend",
    "shape_view",
    "stage_counts",
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


def shape_view(obj: Any, *, load_mesh: bool = True) -> tuple[Any, np.ndarray, np.ndarray]:
    """The scene's one per-shape table: a config shape as meshcat geometry and points.

    ``obj`` is a config shape (the object or an obstacle: ``shape``, ``dims``,
    ``mesh``, ``scale``); every branch on the shape kind in this package's
    scene is here.

    Args:
        obj: The shape.
        load_mesh: Read a ``mesh`` shape's file (False: geometry None, for
            the points alone).

    Returns:
        The meshcat geometry, its transform (4, 4) in the shape's frame, and
        a few points (K, 3) in the shape's frame spanning it (for framing the
        camera; the frame's origin alone for a mesh).

    Raises:
        PublishError: A mesh file that does not exist or has an unsupported format.
    """
    shape = obj.shape
    dims = obj.dims
    if shape == "cylinder":
        r, h = dims.radius, dims.height
        # meshcat cylinders run along y, centred: stand it on its base along z
        local = _translation((0.0, 0.0, h / 2.0))
        local[:3, :3] = ROT_X90
        return mg.Cylinder(h, r), local, np.array([[-r, -r, 0.0], [r, r, h]])
    if shape in ("box", "plane"):
        size = np.zeros(3)
        size[: len(dims.size)] = dims.size
        corners = np.array([-size / 2, size / 2])
        if shape == "box":
            return mg.Box(list(dims.size)), np.eye(4), corners
        # a thin box centred on the frame, as the collision world models it
        sx, sy = dims.size
        return mg.Box([sx, sy, 0.002]), np.eye(4), corners
    if shape == "sphere":
        r = dims.radius
        return mg.Sphere(r), np.eye(4), np.array([[-r] * 3, [r] * 3])
    # mesh
    if not load_mesh:
        return None, np.eye(4), np.zeros((1, 3))
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
    return loaders[ext](str(path)), local, np.zeros((1, 3))


def _object_points(obj: Any) -> np.ndarray:
    """A few world points (K, 3) spanning the object (for framing the camera)."""
    local = shape_view(obj, load_mesh=False)[2]
    m = obj.pose.matrix()
    return local @ m[:3, :3].T + m[:3, 3]


def _draw_object(vis: Any, obj: Any) -> list[str]:
    geometry, local, _ = shape_view(obj)
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
        geometry, local, _ = shape_view(obs)
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
    local = ROT_X90.T @ np.asarray(position, dtype=float)
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
        drawer = RobotDrawer(vis, robot, base)
        qs = _top_solutions(grasps, top_k)
        home = np.asarray(getattr(robot, "home", np.zeros(robot.nq)), dtype=float)
        q0 = qs[0] if len(qs) else home
        drawer.display(q0)
        robot_pts = drawer.joint_points(q0, base)
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
