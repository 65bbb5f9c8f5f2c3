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
``/cloud/<name>``           each scene point cloud (``Points``; RGB, else by
                            segment, else by height; subsampled)
``/contacts``               the grasps' contact points (``Points``, magenta)
=========================== ==================================================

Glyphs are batched, one meshcat object per grasp class
(:mod:`gcm_pipeline.outputs.scene_glyphs`); the object and the environment
are drawn by :mod:`gcm_pipeline.outputs.scene_shapes`, the point clouds and
contact points by :mod:`gcm_pipeline.outputs.scene_cloud`, the robot by
:mod:`gcm_pipeline.outputs.robot_view`, and the camera is placed by
:mod:`gcm_pipeline.outputs.scene_camera`.

The scene takes plain values, :class:`SceneOptions` (and
:class:`PublishOptions` for what is published); :mod:`gcm_pipeline.pipeline`
maps a run's config onto them. The same scene is recorded into a
self-contained page (:mod:`gcm_pipeline.outputs.html`) or sent to a live
meshcat server (:mod:`gcm_pipeline.outputs.live`).
"""

from __future__ import annotations

import warnings
from dataclasses import asdict, dataclass, field
from typing import Any

import numpy as np

from gcm_pipeline.errors import PublishError
from gcm_pipeline.outputs.meshcat_lib import load_meshcat
from gcm_pipeline.outputs.plots import candidate_rows
from gcm_pipeline.outputs.robot_view import ANIMATION_BLEND_LIMIT, RobotDrawer
from gcm_pipeline.outputs.scene_camera import frame_scene, set_camera
from gcm_pipeline.outputs.scene_cloud import SceneCloud, cloud_corners, draw_clouds, draw_contacts
from gcm_pipeline.outputs.scene_glyphs import (
    column,
    draw_grasps,
    grasp_poses,
    legend,
    line_segments,
)
from gcm_pipeline.outputs.scene_shapes import (
    SceneShape,
    SceneTable,
    draw_environment,
    draw_object,
    object_points,
)
from gcm_pipeline.robot.model import Robot
from gcm_pipeline.table import GraspTable

__all__ = [
    "SCENE_PATHS",
    "PublishOptions",
    "SceneInfo",
    "SceneOptions",
    "build_scene",
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
    "/cloud",
    "/contacts",
)


# -- options and results ----------------------------------------------------------------


@dataclass(frozen=True, eq=False)
class SceneOptions:
    """What the scene draws besides the grasps, the manifold and the robot.

    Attributes:
        base_pose: The robot's base in the world (4, 4) [m].
        top_k: Best-ranked solutions in the robot animation.
        blend_limit: Largest joint jump [rad] the animation blends across (one
            IK branch; the run's ``continuity.threshold``); beyond it, it cuts.
        object: The grasped object, or None.
        table: The support table, or None.
        obstacles: The other obstacles of the environment.
        clouds: The scene's point clouds (world frame).
    """

    base_pose: np.ndarray = field(default_factory=lambda: np.eye(4))
    top_k: int = 10
    blend_limit: float = ANIMATION_BLEND_LIMIT
    object: SceneShape | None = None
    table: SceneTable | None = SceneTable()
    obstacles: tuple[SceneShape, ...] = ()
    clouds: tuple[SceneCloud, ...] = ()

    def __post_init__(self) -> None:
        base = np.array(self.base_pose, dtype=float)
        base.setflags(write=False)
        object.__setattr__(self, "base_pose", base)
        object.__setattr__(self, "obstacles", tuple(self.obstacles))
        object.__setattr__(self, "clouds", tuple(self.clouds))


@dataclass(frozen=True, eq=False)
class PublishOptions:
    """What is published, and the scene it shows.

    Attributes:
        scene: The scene's options.
        html: Write ``scene.html``.
        plots: Write the PNG plots.
        zmq_url: The live viewer's meshcat server (None: start one on 127.0.0.1).
        connect_timeout_s: Time bound of the first answer of that server [s].
    """

    scene: SceneOptions = field(default_factory=SceneOptions)
    html: bool = True
    plots: bool = True
    zmq_url: str | None = None
    connect_timeout_s: float = 5.0


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
        cloud_points: Points drawn of each point cloud, by name (subsampled).
        contacts: Contact points drawn.
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
    cloud_points: dict[str, int] = field(default_factory=dict)
    contacts: int = 0

    def to_dict(self) -> dict[str, Any]:
        """Return the info as plain JSON-ready data."""
        return asdict(self)


# -- scene parts ------------------------------------------------------------------------


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
    mg = load_meshcat().geometry
    material = mg.MeshLambertMaterial(
        color=0x4A90D9, opacity=0.28, transparent=True, depthWrite=False
    )
    vis["manifold/triangles"].set_object(mg.TriangularMeshGeometry(verts, tris), material)
    edges = np.concatenate([tris[:, [0, 1]], tris[:, [1, 2]], tris[:, [2, 0]]])
    edges = np.unique(np.sort(edges, axis=1), axis=0)
    seg = verts[edges.reshape(-1)]
    colors = np.tile(np.array([[0.16, 0.35, 0.62]], dtype=np.float32), (len(seg), 1))
    vis["manifold/edges"].set_object(line_segments(seg, colors, 1.0))
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
        order = np.flatnonzero(column(grasps, "reachable", False).astype(bool))
    order = order[np.all(np.isfinite(q[order]), axis=1)] if len(order) else order
    return q[order[:k]]


def build_scene(
    vis: Any,
    grasps: GraspTable,
    manifold: Any,
    robot: Robot | None,
    options: SceneOptions,
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
        options: The object, the environment, the robot's base and animation.
        orbit_target: The page sets the orbit controls' target (static HTML).

    Returns:
        What was drawn, with the colour legend and the camera.
    """
    n = len(grasps)
    if n and "dq" not in grasps:
        raise PublishError("grasp table has no 'dq' column; nothing to draw")
    rot, trans = grasp_poses(grasps) if n else (np.empty((0, 3, 3)), np.empty((0, 3)))
    vis.delete()
    paths: list[str] = []
    frame_pts: list[np.ndarray] = []
    base = options.base_pose
    anim_s = 0.0
    cuts = 0
    n_top = 0
    robot_pts = np.zeros((0, 3))
    if robot is not None:
        drawer = RobotDrawer(vis, robot, base)
        qs = _top_solutions(grasps, int(options.top_k))
        home = np.asarray(getattr(robot, "home", np.zeros(robot.nq)), dtype=float)
        q0 = qs[0] if len(qs) else home
        drawer.display(q0)
        robot_pts = drawer.joint_points(q0, base)
        frame_pts.append(robot_pts)
        if len(qs) > 1:
            anim_s, cuts = drawer.animate(vis, qs, float(options.blend_limit))
        n_top = len(qs)
        paths.append("/robot")
    if options.object is not None:
        paths += draw_object(vis, options.object)
        frame_pts.append(object_points(options.object))
    paths += draw_environment(vis, options.table, options.obstacles)
    cloud_paths, cloud_points = draw_clouds(vis, options.clouds)
    paths += cloud_paths
    if cloud_points:
        frame_pts.append(cloud_corners(options.clouds))
    contact_paths, n_contacts = draw_contacts(vis, grasps)
    paths += contact_paths
    gpaths, glyph, n_r, n_u = draw_grasps(vis, grasps, rot, trans) if n else ([], "none", 0, 0)
    paths += gpaths
    paths += _draw_manifold(vis, grasps, manifold, trans)
    others = np.concatenate(frame_pts) if frame_pts else np.zeros((1, 3))
    target, position = frame_scene(trans, others, robot_pts, orbit_target=orbit_target)
    set_camera(vis, position)
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
        cloud_points=cloud_points,
        contacts=n_contacts,
    )


# -- counts ---------------------------------------------------------------------------


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
        "reachable": int(column(grasps, "reachable", False).astype(bool).sum()),
    }
