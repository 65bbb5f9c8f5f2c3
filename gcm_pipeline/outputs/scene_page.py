"""The page around the meshcat viewer: legend, layer toggles, top-k list, picking, motion.

``scene.html`` is meshcat's static viewer with the scene's commands baked in
(:mod:`gcm_pipeline.outputs.html`) and, beside it, a side panel written by
the page's own script (``assets/scene_page.js``, ``assets/scene_page.css``),
fed by one JSON document (:func:`page_data`):

- **Legend and layers**: one row per scene layer (:func:`scene_layers`) with
  its colour, its count and a checkbox that toggles exactly that meshcat
  path, grouped reachable (rank bands) / unreachable (by reason) / scene; the
  manipulability colour bar with its range.
- **Top-k list**: the best-ranked grasps (rank, manipulability, clearance).
- **Picking**: a click in the 3-D view picks the nearest drawn grasp within
  :data:`PICK_RADIUS_PX` on screen (grasp positions projected with the
  camera), reachable grasps first. A reachable grasp (or a top-k entry) poses
  the arm at its ``q`` and plays its approach ``q_pregrasp -> q`` and its
  retreat ``q -> q_retreat`` (joint-space lines between the stored
  configurations, as the tour does), then rests at ``q``; an unreachable one
  shows its reason and, when the run kept one, poses the rejected solution
  ``q_rejected``, marked as such.
- **Forward kinematics in the page**: the arm is posed from the robot's
  kinematic tree (:func:`~gcm_pipeline.outputs.robot_view.kinematic_tree`:
  joint placements, kinds, axes of the Pinocchio model), so any pose is
  exact, not precomputed. For a model with a joint type the page does not
  know, the :data:`FALLBACK_LIMIT` best grasps are posed from visual
  placements computed here (no motion; the panel says so).

The pickable grasps are capped (:data:`PICK_LIMIT` reachable ones by rank and
as many unreachable ones, evenly spread), their configurations stored as
base64 float64 (exact: ``q``, ``q_pregrasp``, ``q_retreat`` of the reachable
ones, ``q_rejected`` of the unreachable ones), positions as float32.

The top-k tour (:func:`set_tour`) replaces the scene's animation: per grasp
the approach, the grasp held and the retreat, then a cut to the next grasp
(:func:`~gcm_pipeline.outputs.robot_view.tour_keys`).
"""

from __future__ import annotations

import base64
import dataclasses
import json
from importlib import resources
from typing import Any

import numpy as np

from gcm_pipeline.geometry.dualquat import dq_to_matrix
from gcm_pipeline.outputs.plots import colormap
from gcm_pipeline.outputs.robot_view import ROT_X90, RobotPoser, kinematic_tree, tour_keys
from gcm_pipeline.outputs.scene import SceneInfo, SceneOptions
from gcm_pipeline.outputs.scene_glyphs import column
from gcm_pipeline.robot.model import Robot
from gcm_pipeline.table import GraspTable

__all__ = [
    "FALLBACK_LIMIT",
    "PICK_LIMIT",
    "PICK_RADIUS_PX",
    "page_assets",
    "page_data",
    "scene_layers",
    "set_tour",
]

#: Pickable grasps of each kind (reachable by rank, unreachable spread evenly).
PICK_LIMIT = 2000
#: Reachable grasps posed from precomputed placements when the page cannot move the
#: robot's joints (a joint type its forward kinematics does not know).
FALLBACK_LIMIT = 200
#: A click picks the nearest drawn grasp within this distance on screen [CSS px].
PICK_RADIUS_PX = 12.0
_FPS = 30


# -- layers ---------------------------------------------------------------------------


def scene_layers(info: SceneInfo) -> list[dict[str, Any]]:
    """The scene's layers (``info.layers``), each a fresh dict.

    Each layer: ``{"path", "group", "label", "color", "count", "visible"}``
    (``group``: ``reachable``, ``unreachable`` or ``scene``).
    """
    return [dict(layer) for layer in info.layers]


# -- the tour -------------------------------------------------------------------------


def _ranked_rows(grasps: GraspTable, posable: bool = True) -> np.ndarray:
    """Rows of the reachable grasps best first (by ``rank``; then the unranked ones).

    With ``posable`` only rows with a finite ``q`` (none without the column).
    """
    n = len(grasps)
    if not n or (posable and "q" not in grasps):
        return np.zeros(0, dtype=np.int64)
    reach = column(grasps, "reachable", False).astype(bool)
    if "rank" in grasps:
        rank = np.asarray(grasps["rank"], dtype=np.int64)
        ranked = np.flatnonzero(rank > 0)
        ranked = ranked[np.argsort(rank[ranked], kind="stable")]
        rows = np.concatenate([ranked, np.flatnonzero(reach & (rank <= 0))])
    else:
        rows = np.flatnonzero(reach)
    if posable and len(rows):
        q = np.asarray(grasps["q"], dtype=float).reshape(n, -1)
        rows = rows[np.all(np.isfinite(q[rows]), axis=1)]
    return rows.astype(np.int64)


def _configs(grasps: GraspTable, name: str, rows: np.ndarray) -> np.ndarray | None:
    if name not in grasps:
        return None
    return np.asarray(grasps[name], dtype=float).reshape(len(grasps), -1)[rows]


def set_tour(
    vis: Any,
    grasps: GraspTable,
    poser: RobotPoser,
    options: SceneOptions,
    info: SceneInfo,
) -> tuple[SceneInfo, list[dict[str, Any]]]:
    """Set the top-k tour on ``vis`` (replacing the scene's animation).

    Returns:
        ``info`` with the tour's ``animation_s`` and ``animation_cuts``, and the
        tour's segments ``{"row", "rank", "start_s", "end_s", "approach",
        "retreat"}`` (row of the grasp table, times in the animation [s]).
    """
    rows = _ranked_rows(grasps)[: int(options.top_k)]
    if not len(rows):
        return info, []
    q = _configs(grasps, "q", rows)
    pre = _configs(grasps, "q_pregrasp", rows)
    ret = _configs(grasps, "q_retreat", rows)
    assert q is not None
    tour = tour_keys(q, pre, ret, float(options.blend_limit))
    if not tour.moves:
        return dataclasses.replace(info, animation_s=0.0, animation_cuts=0), []
    anim_s, cuts = poser.animate(vis, q, float(options.blend_limit), pre, ret)
    rank = np.asarray(grasps["rank"])[rows] if "rank" in grasps else np.arange(1, len(rows) + 1)
    segments = [
        {
            "row": int(rows[s.index]),
            "rank": int(rank[s.index]),
            "start_s": s.start / _FPS,
            "end_s": s.end / _FPS,
            "approach": s.approach,
            "retreat": s.retreat,
        }
        for s in tour.segments
    ]
    return dataclasses.replace(info, animation_s=anim_s, animation_cuts=cuts), segments


# -- the page's data ------------------------------------------------------------------


def _b64(arr: np.ndarray, dtype: str) -> dict[str, Any]:
    a = np.ascontiguousarray(arr, dtype=dtype)
    return {
        "dtype": dtype,
        "shape": list(a.shape),
        "b64": base64.b64encode(a.astype(a.dtype.newbyteorder("<")).tobytes()).decode("ascii"),
    }


def _finite_or_none(values: np.ndarray) -> list[float | None]:
    return [float(v) if np.isfinite(v) else None for v in np.asarray(values, dtype=float)]


def _pickable(grasps: GraspTable) -> tuple[np.ndarray, int]:
    """Rows the page can pick (reachable by rank, then unreachable), and how many reachable."""
    reach = column(grasps, "reachable", False).astype(bool)
    ranked = _ranked_rows(grasps, posable=False)[:PICK_LIMIT]
    unreach = np.flatnonzero(~reach)
    if len(unreach) > PICK_LIMIT:
        unreach = unreach[np.linspace(0, len(unreach) - 1, PICK_LIMIT).astype(np.int64)]
    return np.concatenate([ranked, unreach]).astype(np.int64), len(ranked)


def _grasp_layers(
    layers: list[dict[str, Any]], legend: dict[str, Any], reach: np.ndarray, reason: np.ndarray
) -> list[int]:
    """Index of the layer that draws each picked grasp (-1: none).

    The picks are ordered best first, so the first ``count`` reachable ones are the
    top band's; an unreachable grasp is in its reason's layer (the legend's ``path``).
    """
    index = {layer["path"]: i for i, layer in enumerate(layers)}
    top = index.get("/grasps/reachable/top")
    n_top = int(layers[top]["count"] or 0) if top is not None else 0
    reason_path = {
        str(r): str(v.get("path", "")) for r, v in (legend.get("unreachable") or {}).items()
    }
    out = []
    for k, (r, why) in enumerate(zip(reach, reason, strict=True)):
        if r:
            path = "/grasps/reachable/top" if k < n_top else "/grasps/reachable/rest"
        else:
            path = reason_path.get(str(why), "")
        out.append(index.get(path, -1))
    return out


def _fallback_placements(grasps: GraspTable, poser: RobotPoser, rows: np.ndarray) -> dict[str, Any]:
    """Visual placements (m, V * 16, row-major) at ``q`` of the best :data:`FALLBACK_LIMIT` rows.

    For a robot whose joint types the page cannot move: those grasps are posed
    from these (no motion); a row without a finite ``q`` gets NaN.
    """
    q = np.asarray(grasps["q"], dtype=float).reshape(len(grasps), -1)[rows[:FALLBACK_LIMIT]]
    n_vis = len(poser.visual.geometryObjects)
    out = np.full((len(q), n_vis * 16), np.nan)
    for i, qi in enumerate(q):
        if np.all(np.isfinite(qi)):
            out[i] = np.concatenate([t.reshape(-1) for _, t in poser.placements(qi)])
    return _b64(out, "<f8")


def _colorbar(legend: dict[str, Any]) -> dict[str, Any]:
    name = str(legend.get("colormap", "viridis"))
    cmap = colormap(name)
    stops = [
        "#" + "".join(f"{int(round(255 * c)):02x}" for c in cmap(t)[:3])
        for t in np.linspace(0.0, 1.0, 11)
    ]
    return {
        "colormap": name,
        "range": [float(v) for v in legend.get("metric_range", [0.0, 1.0])],
        "stops": stops,
        "metric": "manipulability",
    }


def page_data(
    grasps: GraspTable,
    robot: Robot | None,
    options: SceneOptions,
    info: SceneInfo,
    *,
    poser: RobotPoser | None = None,
    tour: list[dict[str, Any]] | None = None,
) -> dict[str, Any]:
    """The JSON document the page's script reads (see the module docstring).

    Args:
        grasps: The grasp table (``dq`` required when not empty).
        robot: The robot (its kinematic tree is exported), or None.
        options: The scene's options (``top_k``, ``base_pose``).
        info: What the scene drew (its layers, legend, camera).
        poser: The robot's visual poses (built from ``robot`` when None).
        tour: The tour's segments (:func:`set_tour`).

    Returns:
        Plain JSON-ready data.
    """
    n = len(grasps)
    layers = scene_layers(info)
    rows, n_reach = _pickable(grasps)
    reach = np.arange(len(rows)) < n_reach
    reason = column(grasps, "reason", "").astype(str)[rows]
    reason = np.where(~reach & (reason == ""), "no_ik", reason)
    pos = np.zeros((0, 3))
    if n:
        pos = dq_to_matrix(np.asarray(grasps["dq"], dtype=float)[rows])[:, :3, 3]
    picked: dict[str, Any] = {
        "row": rows.tolist(),
        "reachable": reach.tolist(),
        "reason": reason.tolist(),
        "position": _b64(pos.reshape(-1, 3), "<f4"),
        "layer": _grasp_layers(layers, info.legend or {}, reach, reason),
    }
    for name in ("rank", "manipulability", "clearance"):
        if name in grasps:
            col = np.asarray(grasps[name], dtype=float)[rows]
            picked[name] = _finite_or_none(col)
    # configurations of the reachable picks (first), rejected ones of the unreachable (after)
    for name, part in (
        ("q", rows[:n_reach]),
        ("q_pregrasp", rows[:n_reach]),
        ("q_retreat", rows[:n_reach]),
        ("q_rejected", rows[n_reach:]),
    ):
        if name in grasps:
            picked[name] = _b64(np.asarray(grasps[name], dtype=float).reshape(n, -1)[part], "<f8")
    kin = None
    if robot is not None:
        poser = poser or RobotPoser(robot)
        kin = kinematic_tree(poser, getattr(robot, "grasp_frame_id", None))
        if kin["unsupported"] and "q" in grasps:
            kin["placements"] = _fallback_placements(grasps, poser, rows[:n_reach])
    base = np.asarray(options.base_pose, dtype=float)
    return {
        "counts": {
            "total": n,
            "reachable": int(column(grasps, "reachable", False).astype(bool).sum()),
            "pickable": len(rows),
        },
        "layers": layers,
        "legend": info.legend,
        "colorbar": _colorbar(info.legend or {}),
        "top_k": int(min(options.top_k, n_reach)),
        "grasps": picked,
        "kinematics": kin,
        "base": [float(v) for v in base.reshape(-1)],
        "root": [float(v) for v in _root().reshape(-1)],
        "tour": tour or [],
        "animation_s": float(info.animation_s),
        "blend_limit": float(options.blend_limit),
        "pick_radius_px": PICK_RADIUS_PX,
        "pick_limit": PICK_LIMIT,
        "fallback_limit": FALLBACK_LIMIT,
    }


def _root() -> np.ndarray:
    """The meshcat root's transform (z-up world into three.js's y-up), 4 x 4."""
    root = np.eye(4)
    root[:3, :3] = ROT_X90.T
    return root


# -- the page's parts -----------------------------------------------------------------


def page_assets() -> tuple[str, str]:
    """The page's script and style sheet (package data)."""
    folder = resources.files("gcm_pipeline.outputs") / "assets"
    js = (folder / "scene_page.js").read_text(encoding="utf-8")
    css = (folder / "scene_page.css").read_text(encoding="utf-8")
    return js, css


def _plain(value: Any) -> Any:
    """A NumPy scalar or array as plain JSON data (for layers given by the scene)."""
    if isinstance(value, np.ndarray | np.generic):
        return value.tolist()
    raise TypeError(f"{type(value).__name__} is not JSON data")


def data_script(data: dict[str, Any]) -> str:
    """``data`` as an inert JSON script element (every ``<`` escaped: no tag can end it)."""
    text = json.dumps(data, separators=(",", ":"), allow_nan=False, default=_plain)
    text = text.replace("<", "\\u003c")
    return f'<script id="gcm-data" type="application/json">{text}</script>'
