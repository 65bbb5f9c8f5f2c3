"""The grasps in the scene: batched gripper glyphs and their colour legend.

Each grasp class is one meshcat ``LineSegments`` object with per-vertex
colours, so the number of meshcat objects does not depend on the number of
grasps N: reachable grasps coloured by manipulability (viridis), unreachable
ones grey for ``no_ik`` and a fixed colour per other ``reason``. Above
:data:`FULL_GLYPH_LIMIT` grasps the gripper glyph (4 segments) becomes an
approach stick (1 segment) to keep the scene light.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np

from gcm_pipeline.geometry.dualquat import dq_to_matrix
from gcm_pipeline.outputs.meshcat_lib import load_meshcat
from gcm_pipeline.outputs.plots import colormap, reason_palette
from gcm_pipeline.table import GraspTable

__all__ = [
    "FULL_GLYPH_LIMIT",
    "column",
    "draw_grasps",
    "grasp_poses",
    "legend",
    "line_segments",
]

#: Above this many grasps in one class the gripper glyph becomes an approach stick.
FULL_GLYPH_LIMIT = 20_000

_COLORMAP = "viridis"

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


def column(grasps: GraspTable, name: str, default: Any) -> np.ndarray:
    """Column ``name`` of ``grasps`` as an array, or ``default`` in every row without it."""
    col = grasps.get(name)
    if col is None:
        return np.full(len(grasps), default)
    return np.asarray(col)


def _classes(grasps: GraspTable) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Reachable mask, reasons (str) and manipulability (float) of every row."""
    n = len(grasps)
    reachable = column(grasps, "reachable", False).astype(bool)
    reason = column(grasps, "reason", "").astype(str)
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
    return colormap(_COLORMAP)


def grasp_poses(grasps: GraspTable) -> tuple[np.ndarray, np.ndarray]:
    """Rotations (N, 3, 3) and positions (N, 3) of the grasp frames in the world."""
    m = dq_to_matrix(np.asarray(grasps["dq"], dtype=float))
    return m[:, :3, :3], m[:, :3, 3]


def _glyph_segments(rot: np.ndarray, trans: np.ndarray, template: np.ndarray) -> np.ndarray:
    """World vertices (N * V, 3) float32 of a glyph template (V, 3) at N poses."""
    pts = np.einsum("nij,vj->nvi", rot.astype(np.float32), template.astype(np.float32))
    pts += trans.astype(np.float32)[:, None, :]
    return pts.reshape(-1, 3)


def line_segments(vertices: np.ndarray, colors: np.ndarray, linewidth: float = 1.0) -> Any:
    """One meshcat ``LineSegments`` object: vertex pairs (2 S, 3), colours (2 S, 3) in [0, 1]."""
    mg = load_meshcat().geometry
    geometry = mg.PointsGeometry(
        np.ascontiguousarray(vertices.T, dtype=np.float32),
        np.ascontiguousarray(colors.T, dtype=np.float32),
    )
    material = mg.LineBasicMaterial(vertexColors=True, linewidth=linewidth)
    return mg.LineSegments(geometry, material)


def draw_grasps(
    vis: Any, grasps: GraspTable, rot: np.ndarray, trans: np.ndarray
) -> tuple[list[str], str, int, int]:
    """Draw the reachable and the unreachable grasps at their poses (``rot``, ``trans``).

    Returns:
        The scene paths drawn, the glyph (``"gripper"`` or ``"stick"``), and the
        numbers of reachable and unreachable grasps.
    """
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
        vis["grasps/reachable"].set_object(line_segments(verts, colors, 2.0))
        paths.append("/grasps/reachable")
    if n_u:
        unreach = reason[~reachable]
        palette = reason_palette(list(np.unique(unreach)))
        names = list(palette)
        table = np.array([palette[n] for n in names], dtype=np.float32)
        idx = np.searchsorted(np.array(names), unreach)
        verts = _glyph_segments(rot[~reachable], trans[~reachable], template)
        colors = np.repeat(table[idx], nv, axis=0)
        vis["grasps/unreachable"].set_object(line_segments(verts, colors, 1.0))
        paths.append("/grasps/unreachable")
    return paths, glyph, n_r, n_u
