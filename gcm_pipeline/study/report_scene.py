"""The 3-D scene of ``study.html``: the best placement's scene and the per-placement records.

The scene is the run's scene (:func:`~gcm_pipeline.outputs.scene.build_scene`
with the best placement's config and robot) recorded without a server; its
``/grasps`` are replaced by ``/study_grasps/o<k>``, one ``LineSegments`` per
object holding a gripper glyph per grasp of that object in the object's
frame, so that every placement of the object recolours the same glyphs.
:meth:`StudyScene.placement_record` turns a part file into what the page
needs to show that placement: its object and base transforms (column-major,
as three.js reads them), one status byte per grasp and the robot's visual
placements at ``q_best``.

The scene is recorded by :class:`gcm_pipeline.outputs.html.RecordingWindow`,
which keeps the scene tree as ``meshcat-server`` does; its commands are
replayed in the page.
"""

from __future__ import annotations

import base64
import dataclasses
import json
import logging
import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import numpy as np

from gcm_pipeline.config.robot_spec import load_robot
from gcm_pipeline.config.run import load_config
from gcm_pipeline.errors import GcmError
from gcm_pipeline.geometry.dualquat import dq_from_matrix, dq_from_pos_quat, dq_to_matrix
from gcm_pipeline.outputs.html import RecordingWindow
from gcm_pipeline.outputs.meshcat_lib import load_meshcat
from gcm_pipeline.outputs.plots import reason_palette
from gcm_pipeline.outputs.robot_view import RobotDrawer
from gcm_pipeline.outputs.scene import build_scene
from gcm_pipeline.outputs.scene_glyphs import GripperGlyph, line_segments
from gcm_pipeline.outputs.scene_shapes import draw_object
from gcm_pipeline.pipeline import place_file_object
from gcm_pipeline.pipeline.outputs import scene_options
from gcm_pipeline.study.spec import load_study
from gcm_pipeline.table import GraspTable

if TYPE_CHECKING:
    from gcm_pipeline.study.report import StudyReport

__all__ = ["REACHABLE_RGB", "UNKNOWN_RGB", "StudyScene", "build_study_scene", "pose_matrices"]

log = logging.getLogger(__name__)

#: Colour of a reachable grasp; of an unreachable one whose part records no reason.
REACHABLE_RGB = (0.17, 0.63, 0.17)
UNKNOWN_RGB = (0.55, 0.55, 0.55)


def pose_matrices(pose7: np.ndarray) -> np.ndarray:
    """Transforms (N, 4, 4) of poses (N, 7) ``x, y, z, qw, qx, qy, qz`` (zero quat: identity)."""
    p = np.asarray(pose7, dtype=float).reshape(-1, 7)
    quat = np.where(np.all(p[:, 3:] == 0.0, axis=1)[:, None], [1.0, 0.0, 0.0, 0.0], p[:, 3:])
    return dq_to_matrix(dq_from_pos_quat(p[:, :3], quat, check=False))


def _colmajor(m: np.ndarray) -> list[float]:
    return [round(float(v), 6) for v in np.asarray(m).flatten(order="F")]


def _rz(deg: float) -> np.ndarray:
    c, s = math.cos(math.radians(deg)), math.sin(math.radians(deg))
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


class _NullVis:
    """A visualizer that draws nothing (a :class:`RobotDrawer` only for its placements)."""

    def __getitem__(self, path: str) -> _NullVis:
        return self

    def set_object(self, *args: Any, **kwargs: Any) -> None:
        """Draw nothing."""

    def set_transform(self, *args: Any, **kwargs: Any) -> None:
        """Move nothing."""


@dataclass
class StudyScene:
    """The recorded scene and what turns a placement's part into the page's record.

    Attributes:
        commands: meshcat commands (base64 msgpack) that draw the best placement.
        objects: Per object ``{"name", "path", "n", "shape"}`` (its glyph object,
            grasps, and the scene path of its shape: ``""`` when not drawn).
        classes: Per status byte ``{"name", "rgb"}``: 0 reachable, then reasons.
        links: Scene paths of the robot's visual objects (``robot/visuals/<name>``).
        message: Why there is no 3-D scene ("" when there is one).
        camera_target: The orbit target (world [m]).
    """

    commands: list[str] = field(default_factory=list)
    objects: list[dict[str, Any]] = field(default_factory=list)
    classes: list[dict[str, Any]] = field(default_factory=list)
    links: list[str] = field(default_factory=list)
    message: str = ""
    camera_target: list[float] = field(default_factory=lambda: [0.0, 0.0, 0.0])
    _drawer: Any = None
    _nq: int = 0
    _base: np.ndarray = field(default_factory=lambda: np.eye(4))
    _best_yaw: float = 0.0
    _refs: dict[str, np.ndarray] = field(default_factory=dict)
    _home: list[list[float]] | None = None

    def placement_record(
        self, row: Mapping[str, Any], arrays: Mapping[str, np.ndarray]
    ) -> dict[str, Any]:
        """What the page needs to show placement ``row`` (see the module docstring)."""
        names = [c["name"] for c in self.classes]
        mask = np.asarray(arrays["reachable_mask"], dtype=bool)
        if "reason_code" in arrays:
            lut = np.array([0] + [names.index(str(n)) for n in arrays["reason_names"]])
            status = lut[np.asarray(arrays["reason_code"], dtype=np.int64)]
        else:
            status = np.where(mask, 0, names.index("unreachable"))
        obj = str(row.get("object", ""))
        ref = self._refs.get(obj)
        pose_obj = np.asarray(arrays["pose_object"], dtype=float)
        same = ref is not None and ref.shape == pose_obj.shape and np.allclose(ref, pose_obj)
        rec: dict[str, Any] = {
            "obj": _colmajor(self._object_pose(row, arrays)),
            "base": _colmajor(self._base_pose(row)),
            "same": bool(same),
            "status": base64.b64encode(status.astype(np.uint8).tobytes()).decode("ascii"),
            "links": self._home,
        }
        q = np.asarray(arrays.get("q_best", np.empty(0)), dtype=float)
        if self._drawer is not None and q.shape == (self._nq,) and np.all(np.isfinite(q)):
            rec["links"] = [_colmajor(t) for _, t in self._drawer.placements(q)]
        return rec

    @staticmethod
    def _object_pose(row: Mapping[str, Any], arrays: Mapping[str, np.ndarray]) -> np.ndarray:
        pose, local = np.asarray(arrays["pose"]), np.asarray(arrays["pose_object"])
        if len(pose):  # exact: the world pose of a grasp times its pose in the object
            return pose_matrices(pose[:1])[0] @ np.linalg.inv(pose_matrices(local[:1])[0])
        m = np.eye(4)
        m[:3, :3] = _rz(float(row.get("object_yaw_deg") or 0.0))
        m[:3, 3] = [float(row.get(f"object_{a}") or 0.0) for a in "xyz"]
        return m

    def _base_pose(self, row: Mapping[str, Any]) -> np.ndarray:
        m = self._base.copy()
        yaw = row.get("base_yaw_deg")
        if yaw is not None:
            m[:3, :3] = _rz(float(yaw) - self._best_yaw) @ m[:3, :3]
        for i, a in enumerate("xyz"):
            v = row.get(f"base_{a}")
            if v is not None:
                m[i, 3] = float(v)
        return m


def _classes(report: StudyReport) -> list[dict[str, Any]]:
    reasons = sorted(
        {str(n) for a in report.parts.values() for n in a.get("reason_names", ())} - {""}
    )
    palette = reason_palette(reasons)
    out = [{"name": "reachable", "rgb": list(REACHABLE_RGB)}]
    out += [{"name": r, "rgb": [round(float(c), 3) for c in palette[r]]} for r in reasons]
    if "unreachable" not in reasons:
        out.append({"name": "unreachable", "rgb": list(UNKNOWN_RGB)})
    return out


def _plan(report: StudyReport) -> Any:
    """The study's plan, from the study file ``study.json`` names."""
    meta = json.loads((report.path / "study.json").read_text(encoding="utf-8"))
    if not isinstance(meta, dict) or not meta.get("source"):
        raise GcmError("study.json names no study file")
    return load_study(meta["source"])


def _placement_config(plan: Any, row: Mapping[str, Any]) -> Any:
    """A placement's config as its run saw it (an object its grasp file names, placed)."""
    cfg = plan.resolve(list(row.get("overrides") or []), where=f"placement {row['id']}")
    return place_file_object(cfg) if cfg.object is None else cfg


def _best_config(report: StudyReport) -> Any:
    """The best placement's config: ``best/config.yaml``, else the study file's."""
    best = report.best
    assert best is not None
    path = report.path / "best" / "config.yaml"
    if path.is_file():
        cfg = load_config(path)
        return place_file_object(cfg) if cfg.object is None else cfg
    return _placement_config(_plan(report), best)


def _draw_other_objects(scene: StudyScene, report: StudyReport, vis: Any) -> None:
    """Draw the shape of every object but the best placement's under ``/study_objects/o<k>``."""
    best = str(report.best["object"]) if report.best else ""
    for o in scene.objects:
        o["shape"] = "object" if o["name"] == best else ""
    others = [o for o in scene.objects if not o["shape"]]
    if not others:
        return
    try:
        plan = _plan(report)
    except (GcmError, OSError, ValueError) as exc:
        log.warning("study report: other objects' shapes not drawn: %s", exc)
        return
    for o in others:
        row = next(r for r in report.rows if str(r["object"]) == o["name"])
        try:
            shape = scene_options(_placement_config(plan, row)).object
        except (GcmError, OSError, ValueError) as exc:
            log.warning("study report: %s not drawn: %s", o["name"], exc)
            continue
        if shape is not None:
            node = f"study_objects/{o['path'].rsplit('/', 1)[-1]}"
            draw_object(vis[node], shape)
            vis[f"{node}/object"].set_property("visible", False)
            o["shape"] = f"{node}/object"


def _glyphs(
    pose_object: np.ndarray,
    status: np.ndarray,
    classes: list[dict[str, Any]],
    gripper: GripperGlyph,
) -> Any:
    """One ``LineSegments``: the gripper's outline per grasp (object frame), coloured by status."""
    mats = pose_matrices(pose_object)
    template = gripper.template()
    verts = np.einsum("nij,vj->nvi", mats[:, :3, :3], template) + mats[:, None, :3, 3]
    rgb = np.array([c["rgb"] for c in classes], dtype=float)
    colours = np.repeat(rgb[np.minimum(status, len(rgb) - 1)], len(template), axis=0)
    return line_segments(verts.reshape(-1, 3), colours, 1.0)


def build_study_scene(report: StudyReport) -> StudyScene:
    """Record the best placement's scene with one glyph object per object.

    A scene that cannot be built (no finished placement, its config or robot
    cannot be read) leaves ``message`` set and no commands; the page still
    shows the maps and the table.
    """
    scene = StudyScene(classes=_classes(report))
    first: dict[str, int] = {}
    for r in report.rows:
        part = report.parts.get(int(r["id"]), {})
        if "pose_object" in part and str(r["object"]) not in first:  # finished, not failed
            first[str(r["object"])] = int(r["id"])
    scene._refs = {o: np.asarray(report.parts[p]["pose_object"]) for o, p in first.items()}
    scene.objects = [
        {"name": o, "path": f"study_grasps/o{k}", "n": len(scene._refs[o])}
        for k, o in enumerate(first)
    ]
    if report.best is None:  # every placement failed: the maps and the table say so
        scene.message = "no 3-D scene: no placement finished"
        return scene
    try:
        cfg = _best_config(report)
        robot = load_robot(cfg.robot.spec, cfg.robot.tool)
    except (GcmError, OSError, ValueError) as exc:
        scene.message = f"no 3-D scene: {' '.join(str(exc).split())[:300]}"
        log.warning("study report: %s", scene.message)
        return scene
    _record(scene, report, cfg, robot)
    return scene


def _record(scene: StudyScene, report: StudyReport, cfg: Any, robot: Any) -> None:
    """Draw the best placement's scene into a recording and keep what the records need."""
    best = report.best
    assert best is not None
    # no painted object: its paint is one placement's, and the page moves the object
    opts = dataclasses.replace(scene_options(cfg), paint=False)
    a = report.parts[int(best["id"])]
    table = GraspTable(
        {
            "dq": dq_from_matrix(pose_matrices(a["pose"])),
            "reachable": np.asarray(a["reachable_mask"], dtype=bool),
        }
    )
    window = RecordingWindow()
    vis = load_meshcat().Visualizer(window=window)
    info = build_scene(vis, table, None, robot, opts, orbit_target=True)
    vis["grasps"].delete()
    scene._base = np.asarray(opts.base_pose, dtype=float)
    scene._best_yaw = float(best.get("base_yaw_deg") or 0.0)
    scene._drawer = RobotDrawer(_NullVis(), robot, scene._base)
    scene._nq = int(robot.nq)
    home = np.asarray(getattr(robot, "home", np.zeros(robot.nq)), dtype=float)
    placed = scene._drawer.placements(home)
    scene.links = [path for path, _ in placed]
    scene._home = [_colmajor(t) for _, t in placed]
    _draw_other_objects(scene, report, vis)
    for o in scene.objects:
        status = np.zeros(o["n"], dtype=np.int64)
        vis[o["path"]].set_object(
            _glyphs(scene._refs[o["name"]], status, scene.classes, opts.gripper)
        )
    scene.commands = [base64.b64encode(b).decode("ascii") for b in window.commands()]
    scene.camera_target = [float(v) for v in info.camera["target"]]
