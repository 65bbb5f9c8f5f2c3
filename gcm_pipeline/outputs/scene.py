"""The published scene: what a run's meshcat scene holds and how it is drawn.

The scene holds, under the meshcat root, one path per layer that the page
shows or hides alone (:attr:`SceneInfo.layers`):

================================== ==============================================
path                               content
================================== ==============================================
``/robot``                         the robot's visual geometry (every object of
                                   its visual model: meshes read by trimesh and
                                   simplified, primitives), posed at the
                                   top-ranked solution, and a tour of the top-k
                                   (each grasp's approach, the grasp, its
                                   retreat; a cut to the next grasp)
``/object``                        the grasped object (primitive or mesh)
``/object_reachability``           the object painted by reachability: per
                                   surface point the share of nearby grasps
                                   that are reachable (red 0, blue 1, dark grey
                                   none near; :mod:`~.scene_paint`)
``/environment``                   the support table (``environment.table``) and
                                   the obstacles
``/grasps/reachable/top``          reachable grasps ranked ``1 .. top_k``: the
                                   run's gripper outline, viridis by
                                   manipulability
``/grasps/reachable/rest``         the other reachable grasps
``/grasps/unreachable/<reason>``   unreachable grasps, one path per ``reason``
                                   (``no_ik``, ``collision_self``, ...), one
                                   colour each (:mod:`~.scene_glyphs`)
``/manifold``                      the manifold's triangles (translucent) and
                                   edges
``/cloud/<name>``                  each scene point cloud (``Points``; RGB, else
                                   by segment, else by height; subsampled)
``/contacts``                      the grasps' contact points (``Points``,
                                   magenta)
``/envelope``                      the robot's reach envelope (FK of random
                                   configurations: points and their convex
                                   hull), hidden at first (:mod:`~.scene_envelope`)
================================== ==============================================

A grasp class draws at most :data:`~.scene_glyphs.GLYPH_BUDGET` gripper
glyphs over all classes and the others as dots (level of detail, recorded in
:attr:`SceneInfo.lod`); the layers' counts are always the table's. The object
and the environment are drawn by :mod:`~.scene_shapes`, the point clouds and
contact points by :mod:`~.scene_cloud`, the robot by
:mod:`~.robot_view`, and the camera is placed by :mod:`~.scene_camera`.

The scene takes plain values, :class:`SceneOptions` (and
:class:`PublishOptions` for what is published); :mod:`gcm_pipeline.pipeline`
maps a run's config onto them (the run's gripper onto
:class:`~.scene_glyphs.GripperGlyph`). The same scene is recorded into a
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
from gcm_pipeline.outputs.scene_cloud import (
    CONTACT_COLOR,
    MAX_CLOUD_POINTS,
    SceneCloud,
    cloud_corners,
    contact_points,
    draw_clouds,
    draw_contacts,
)
from gcm_pipeline.outputs.scene_envelope import draw_envelope
from gcm_pipeline.outputs.scene_glyphs import (
    GLYPH_BUDGET,
    POINT_BUDGET,
    GripperGlyph,
    column,
    draw_grasps,
    grasp_positions,
    hex_color,
    legend,
    line_segments,
)
from gcm_pipeline.outputs.scene_paint import draw_paint
from gcm_pipeline.outputs.scene_shapes import (
    OBJECT_COLOR,
    TABLE_COLOR,
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
    "layer",
    "stage_counts",
]

#: Top-level scene paths (relative to the meshcat root); each layer lies at or below one.
SCENE_PATHS = (
    "/robot",
    "/object",
    "/object_reachability",
    "/environment",
    "/grasps/reachable",
    "/grasps/unreachable",
    "/manifold",
    "/cloud",
    "/contacts",
    "/envelope",
)

_MANIFOLD_COLOR = 0x4A90D9


# -- options and results ----------------------------------------------------------------


@dataclass(frozen=True, eq=False)
class SceneOptions:
    """What the scene draws besides the grasps, the manifold and the robot.

    Attributes:
        base_pose: The robot's base in the world (4, 4) [m].
        top_k: Best-ranked solutions in the robot animation, and the top band
            of the reachable grasps (``/grasps/reachable/top``).
        blend_limit: Largest joint jump [rad] of an approach or retreat the tour
            shows as a motion (one IK branch; the run's ``continuity.threshold``);
            beyond it, the tour cuts.
        object: The grasped object, or None.
        table: The support table, or None.
        obstacles: The other obstacles of the environment.
        clouds: The scene's point clouds (world frame).
        gripper: The outline drawn at each grasp (the run's gripper).
        glyph_budget: Most gripper glyphs drawn; the other grasps are dots.
        point_budget: Most grasp dots drawn (a uniform sample beyond).
        paint: Paint the object by reachability (``/object_reachability``).
        envelope: Draw the robot's reach envelope (``/envelope``, hidden at first).
    """

    base_pose: np.ndarray = field(default_factory=lambda: np.eye(4))
    top_k: int = 10
    blend_limit: float = ANIMATION_BLEND_LIMIT
    object: SceneShape | None = None
    table: SceneTable | None = SceneTable()
    obstacles: tuple[SceneShape, ...] = ()
    clouds: tuple[SceneCloud, ...] = ()
    gripper: GripperGlyph = GripperGlyph()
    glyph_budget: int = GLYPH_BUDGET
    point_budget: int = POINT_BUDGET
    paint: bool = True
    envelope: bool = True

    def __post_init__(self) -> None:
        base = np.array(self.base_pose, dtype=float)
        base.setflags(write=False)
        object.__setattr__(self, "base_pose", base)
        object.__setattr__(self, "obstacles", tuple(self.obstacles))
        object.__setattr__(self, "clouds", tuple(self.clouds))
        for key in ("glyph_budget", "point_budget"):
            if int(getattr(self, key)) < 0:
                raise PublishError(f"scene {key} must be >= 0, got {getattr(self, key)}")


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
        n_reachable: Number of reachable grasps in the table.
        n_unreachable: Number of unreachable grasps in the table.
        glyph: The grasp glyph: ``"gripper"`` (a parallel-jaw outline),
            ``"suction"`` (a cup), or ``"none"`` (no grasp).
        meshcat_objects: Number of ``set_object`` commands sent (independent of N
            for a given robot, object and environment).
        legend: Colour legend (see :func:`~.scene_glyphs.legend`).
        camera: ``{"position": [x, y, z], "target": [x, y, z]}`` in the world [m].
        top_k: Number of solutions in the robot animation.
        animation_s: Duration of the robot animation [s].
        animation_cuts: Cuts of the tour (to the next grasp, or over an approach
            or retreat that leaves the IK branch).
        cloud_points: Points drawn of each point cloud, by name (subsampled).
        contacts: Contact points drawn.
        layers: Every toggleable path drawn, in legend order, each
            ``{"path", "group", "label", "color", "count", "visible"}``:
            ``group`` is ``reachable``, ``unreachable`` or ``scene``;
            ``color`` ``#rrggbb`` or None (coloured by a colormap or its own
            colours); ``count`` the grasps of a grasp class (the table's,
            whatever the level of detail), the points of a cloud, contact
            points, painted surface points or envelope samples, the
            triangles of the manifold, the shapes of the environment, 1 for
            the robot and the object; ``visible`` the initial visibility
            (False for ``/envelope``). The two reachable bands are listed
            whenever the table has grasps, with count 0 when empty (nothing
            drawn there); an unreachable reason only when it occurs; other
            layers only when drawn.
        gripper: Name of the gripper whose outline the glyphs are.
        lod: Level of detail: ``{"glyph_budget", "point_budget", "glyphs",
            "points", "classes": {path: {"count", "glyphs", "points"}}}``,
            grasps drawn as glyphs and as dots (the rest are not drawn).
        paint: The object painted by reachability (None without an object or
            grasps; drawn only when ``painted`` > 0, no grasp being near it):
            ``{"points", "painted", "mean", "histogram" (10 bins over [0, 1]),
            "bins", "radius", "spacing", "colormap", "no_data_color"}``.
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
    layers: list[dict[str, Any]] = field(default_factory=list)
    gripper: str = "default"
    lod: dict[str, Any] = field(default_factory=dict)
    paint: dict[str, Any] | None = None

    def to_dict(self) -> dict[str, Any]:
        """Return the info as plain JSON-ready data."""
        return asdict(self)


def layer(
    path: str, label: str, count: int, color: str | None = None, *, visible: bool = True
) -> dict[str, Any]:
    """A scene layer of :attr:`SceneInfo.layers` (group ``scene``)."""
    return {
        "path": path,
        "group": "scene",
        "label": label,
        "color": color,
        "count": int(count),
        "visible": visible,
    }


# -- scene parts ------------------------------------------------------------------------


def _draw_manifold(vis: Any, grasps: GraspTable, manifold: Any, trans: np.ndarray) -> list[dict]:
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
        color=_MANIFOLD_COLOR, opacity=0.28, transparent=True, depthWrite=False
    )
    vis["manifold/triangles"].set_object(mg.TriangularMeshGeometry(verts, tris), material)
    edges = np.concatenate([tris[:, [0, 1]], tris[:, [1, 2]], tris[:, [2, 0]]])
    edges = np.unique(np.sort(edges, axis=1), axis=0)
    seg = verts[edges.reshape(-1)]
    colors = np.tile(np.array([[0.16, 0.35, 0.62]], dtype=np.float32), (len(seg), 1))
    vis["manifold/edges"].set_object(line_segments(seg, colors, 1.0))
    return [layer("/manifold", "manifold triangles", len(tris), f"#{_MANIFOLD_COLOR:06x}")]


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


def _draw_contacts(vis: Any, grasps: GraspTable) -> tuple[list[dict], int]:
    """Contact points at ``/contacts`` (a uniform sample beyond the clouds' budget)."""
    n = len(contact_points(grasps))
    if not n:
        return [], 0
    shown = grasps
    if n > MAX_CLOUD_POINTS:
        rows = np.random.default_rng(0).choice(len(grasps), MAX_CLOUD_POINTS, replace=False)
        shown = grasps.take(np.sort(rows))
    _, drawn = draw_contacts(vis, shown)
    return [layer("/contacts", "contact points", n, hex_color(CONTACT_COLOR))], drawn


@dataclass
class _Robot:
    """What drawing the robot gave: its layers, frame points and animation."""

    layers: list[dict]
    points: np.ndarray
    animation_s: float = 0.0
    cuts: int = 0
    n_top: int = 0


def _draw_robot(vis: Any, grasps: GraspTable, robot: Robot | None, options: SceneOptions) -> _Robot:
    if robot is None:
        return _Robot([], np.zeros((0, 3)))
    base = options.base_pose
    drawer = RobotDrawer(vis, robot, base)
    qs = _top_solutions(grasps, int(options.top_k))
    home = np.asarray(getattr(robot, "home", np.zeros(robot.nq)), dtype=float)
    q0 = qs[0] if len(qs) else home
    drawer.display(q0)
    out = _Robot([layer("/robot", "robot", 1)], drawer.joint_points(q0, base), n_top=len(qs))
    if len(qs) > 1:
        out.animation_s, out.cuts = drawer.animate(vis, qs, float(options.blend_limit))
    if options.envelope:
        out.layers.append(draw_envelope(vis, robot, base))
    return out


def _draw_surroundings(
    vis: Any, grasps: GraspTable, options: SceneOptions, reachable: np.ndarray
) -> tuple[list[dict], list[np.ndarray], dict[str, Any] | None, dict[str, int]]:
    """The object, its paint, the environment and the clouds: layers, frame points, info."""
    layers: list[dict] = []
    frame_pts: list[np.ndarray] = []
    paint_info = None
    obj = options.object
    if obj is not None:
        draw_object(vis, obj)
        layers.append(layer("/object", "object", 1, f"#{OBJECT_COLOR:06x}"))
        frame_pts.append(object_points(obj))
        paint = draw_paint(vis, obj, grasps, reachable) if options.paint and len(grasps) else None
        if paint is not None:
            paint_info = paint.summary()
            if paint_info["painted"]:  # drawn only when a grasp is near the object
                label = "object painted by reachability (share of nearby grasps reachable)"
                layers.append(layer("/object_reachability", label, len(paint.share)))
    env_paths, n_env = draw_environment(vis, options.table, options.obstacles)
    if env_paths:
        color = f"#{TABLE_COLOR:06x}"
        layers.append(layer("/environment", "environment (table, obstacles)", n_env, color))
    _, cloud_points = draw_clouds(vis, options.clouds)
    for name, n in cloud_points.items():
        layers.append(layer(f"/cloud/{name}", f"point cloud {name}", n))
    if cloud_points:
        frame_pts.append(cloud_corners(options.clouds))
    return layers, frame_pts, paint_info, cloud_points


def _top_paths(layers: list[dict]) -> tuple[str, ...]:
    """The top-level paths of the layers that drew something, in :data:`SCENE_PATHS` order."""
    drawn = {p for lay in layers if lay["count"] for p in SCENE_PATHS if _under(lay["path"], p)}
    return tuple(p for p in SCENE_PATHS if p in drawn)


def _under(path: str, top: str) -> bool:
    return path == top or path.startswith(top + "/")


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
            ``manipulability``, ``q``, ``rank``, ``origin``, ``contact_x/y/z``
            used when present).
        manifold: The manifold (``triangles`` (T, 3) candidate ids, ``chart``
            (Nc, 2)) or None.
        robot: The robot, or None to leave it out (and its envelope).
        options: The object, the environment, the robot's base and animation,
            the gripper glyph and the level of detail.
        orbit_target: The page sets the orbit controls' target (static HTML).

    Returns:
        What was drawn: its layers, the colour legend and the camera.
    """
    n = len(grasps)
    if n and "dq" not in grasps:
        raise PublishError("grasp table has no 'dq' column; nothing to draw")
    trans = grasp_positions(grasps) if n else np.empty((0, 3))
    reachable = column(grasps, "reachable", False).astype(bool)
    vis.delete()
    drawn_robot = _draw_robot(vis, grasps, robot, options)
    scene_layers, frame_pts, paint_info, cloud_points = _draw_surroundings(
        vis, grasps, options, reachable
    )
    contact_layers, n_contacts = _draw_contacts(vis, grasps)
    grasp_layers: list[dict] = []
    lod: dict[str, Any] = {}
    if n:
        drawing = draw_grasps(
            vis,
            grasps,
            trans,
            options.gripper,
            int(options.top_k),
            int(options.glyph_budget),
            int(options.point_budget),
        )
        grasp_layers, lod = drawing.layers, drawing.lod
    manifold_layers = _draw_manifold(vis, grasps, manifold, trans)
    layers = grasp_layers + drawn_robot.layers[:1] + scene_layers + manifold_layers
    layers += contact_layers + drawn_robot.layers[1:]
    if len(drawn_robot.points):
        frame_pts.append(drawn_robot.points)
    others = np.concatenate(frame_pts) if frame_pts else np.zeros((1, 3))
    target, position = frame_scene(trans, others, drawn_robot.points, orbit_target=orbit_target)
    set_camera(vis, position)
    return SceneInfo(
        paths=_top_paths(layers),
        n_reachable=int(reachable.sum()),
        n_unreachable=n - int(reachable.sum()),
        glyph=("gripper" if options.gripper.kind == "parallel_jaw" else "suction") if n else "none",
        meshcat_objects=int(getattr(vis.window, "n_objects", -1)),
        legend=legend(grasps),
        camera={"position": position.tolist(), "target": target.tolist()},
        top_k=drawn_robot.n_top,
        animation_s=drawn_robot.animation_s,
        animation_cuts=drawn_robot.cuts,
        cloud_points=cloud_points,
        contacts=n_contacts,
        layers=layers,
        gripper=options.gripper.name,
        lod=lod,
        paint=paint_info,
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
