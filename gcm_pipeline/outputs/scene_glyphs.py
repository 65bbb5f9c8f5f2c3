"""The grasps in the scene: gripper glyphs per class, their level of detail and legend.

Every grasp falls in one class, and each class is one scene path that the
page can show or hide alone:

================================= =============================================
path                              grasps
================================= =============================================
``/grasps/reachable/top``         reachable, ``1 <= rank <= top_k``
``/grasps/reachable/rest``        the other reachable grasps (worse ranks, unranked)
``/grasps/unreachable/<reason>``  unreachable for ``reason`` (``no_ik``,
                                  ``collision_self``, ...; ``unchecked`` without
                                  a ``reachable`` column)
================================= =============================================

A class holds at most two meshcat objects, so their number does not grow with
the grasps: ``<path>/glyphs``, one ``LineSegments`` with the outline of the
run's gripper (:class:`GripperGlyph`: fingers at its opening, palm, approach
stem; a suction cup's lip and body) at each grasp, and ``<path>/points``, one
``Points`` object with a dot at the grasp frame's origin of grasps drawn
without a glyph. Level of detail: at most :data:`GLYPH_BUDGET` glyphs over
all classes, the top band first, then each class a fair share (the
best-ranked reachable grasps first, a uniform sample of each unreachable
class), and at most :data:`POINT_BUDGET` dots for the others (a uniform
sample). Reachable grasps are coloured by manipulability (viridis), the
unreachable ones by reason (:func:`~gcm_pipeline.outputs.plots.reason_palette`,
colours viridis never takes).
"""

from __future__ import annotations

import math
import re
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from gcm_pipeline.errors import PublishError
from gcm_pipeline.geometry.dualquat import dq_to_matrix, dq_translation
from gcm_pipeline.outputs.meshcat_lib import load_meshcat
from gcm_pipeline.outputs.plots import colormap, reason_palette
from gcm_pipeline.table import GraspTable

__all__ = [
    "GLYPH_BUDGET",
    "POINT_BUDGET",
    "REASON_LABELS",
    "GraspClass",
    "GraspDrawing",
    "GripperGlyph",
    "column",
    "draw_grasps",
    "grasp_classes",
    "grasp_positions",
    "hex_color",
    "legend",
    "line_segments",
    "points_object",
]

#: Most gripper glyphs drawn over all classes.
GLYPH_BUDGET = 20_000
#: Most grasps drawn as dots (the ones without a glyph) over all classes.
POINT_BUDGET = 200_000
#: Edge of a grasp dot's square, in world units [m].
POINT_SIZE = 0.004

#: Human label of each unreachable reason (others: the reason with spaces).
REASON_LABELS = {
    "out_of_reach": "out of reach",
    "no_ik": "no IK solution",
    "joint_limits": "joint limits",
    "collision_self": "self-collision",
    "collision_environment": "collides with the environment",
    "collision_object": "collides with the object",
    "approach": "approach path blocked",
    "retreat": "retreat path blocked",
    "unchecked": "not checked",
}

_COLORMAP = "viridis"
_PATH_SAFE = re.compile(r"[^A-Za-z0-9_-]")


@dataclass(frozen=True)
class GripperGlyph:
    """The outline drawn at each grasp, in the grasp frame (z = approach, fingers along y).

    Plain numbers from the run's gripper (``gcm_pipeline.pipeline`` fills them
    in from the gripper registry); the defaults are the Franka Hand's.

    Attributes:
        name: The gripper's name (``default`` when the run names none).
        kind: ``parallel_jaw`` (two fingers) or ``suction`` (a cup).
        opening: Distance between the fingers (the gripper's largest opening) [m].
        finger_length: From the grasp frame's origin back to the palm [m].
        finger_tip: How far the fingertips reach past the origin [m].
        finger_thickness: A finger's size along the closing axis: the palm bar
            spans the fingers' outer faces [m].
        palm_depth: The palm's extent along the approach: the stem's length, at most
            half the opening (:meth:`stem`) [m].
        cup_radius: A suction cup's lip radius [m].
        cup_depth: A suction cup's depth behind its lip (the origin) [m].
    """

    name: str = "default"
    kind: str = "parallel_jaw"
    opening: float = 0.08
    finger_length: float = 0.037
    finger_tip: float = 0.009
    finger_thickness: float = 0.026
    palm_depth: float = 0.092
    cup_radius: float = 0.015
    cup_depth: float = 0.069

    def __post_init__(self) -> None:
        if self.kind not in ("parallel_jaw", "suction"):
            raise PublishError(
                f"gripper glyph {self.name!r}: kind {self.kind!r}; valid: parallel_jaw, suction"
            )
        for key in ("opening", "finger_length", "palm_depth", "cup_radius", "cup_depth"):
            value = getattr(self, key)
            if not (math.isfinite(value) and value > 0.0):
                raise PublishError(f"gripper glyph {self.name!r}: {key} {value!r} is not > 0")
        for key in ("finger_tip", "finger_thickness"):
            value = getattr(self, key)
            if not (math.isfinite(value) and value >= 0.0):
                raise PublishError(f"gripper glyph {self.name!r}: {key} {value!r} is not >= 0")

    def template(self) -> np.ndarray:
        """The outline's segments as vertex pairs (2 S, 3) in the grasp frame [m]."""
        if self.kind == "suction":
            return self._cup()
        h, back = self.opening / 2.0, -self.finger_length
        palm = h + self.finger_thickness
        tick = min(0.25 * self.opening, 0.01)  # the pads, pointing the way the fingers close
        return np.array(
            [
                [0.0, -h, self.finger_tip],
                [0.0, -h, back],
                [0.0, h, self.finger_tip],
                [0.0, h, back],
                [0.0, -palm, back],
                [0.0, palm, back],
                [0.0, 0.0, back],
                [0.0, 0.0, back - self.stem()],
                [0.0, -h, 0.0],
                [0.0, -h + tick, 0.0],
                [0.0, h, 0.0],
                [0.0, h - tick, 0.0],
            ]
        )

    def stem(self) -> float:
        """Length of the approach stem behind the palm [m].

        The palm's depth, at most half the opening, so that many grasps around an
        object read as grippers, not as a brush of long sticks.
        """
        return min(self.palm_depth, 0.5 * self.opening)

    def _cup(self) -> np.ndarray:
        r, d = self.cup_radius, self.cup_depth
        a = np.linspace(0.0, 2.0 * np.pi, 9)
        ring = np.column_stack([r * np.cos(a), r * np.sin(a), np.zeros(9)])
        lip = np.stack([ring[:-1], ring[1:]], axis=1).reshape(-1, 3)
        body = np.array(
            [
                [0.0, -r, 0.0],
                [0.0, -r / 2.0, -d],
                [0.0, r, 0.0],
                [0.0, r / 2.0, -d],
                [0.0, -r / 2.0, -d],
                [0.0, r / 2.0, -d],
                [0.0, 0.0, -d],
                [0.0, 0.0, -d - max(d, 0.03)],
            ]
        )
        return np.concatenate([lip, body])


def hex_color(rgb: Sequence[float]) -> str:
    """``#rrggbb`` of an RGB colour in [0, 1]."""
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
        "reachable": n, "unreachable": {reason: {"color": hex, "count": n,
        "label": text, "path": scene path}}}``. ``metric_range`` is the
        manipulability range over the reachable grasps that the colormap
        spans (``[0, 1]`` when there is none).
    """
    reachable, reason, manip = _classes(grasps)
    vmin, vmax = _manipulability_range(manip[reachable])
    ticks = np.linspace(vmin, vmax, 5)
    cmap = colormap(_COLORMAP)
    names, counts = np.unique(reason[~reachable], return_counts=True)
    palette = reason_palette(list(names))
    return {
        "colormap": _COLORMAP,
        "metric_range": [vmin, vmax],
        "ticks": [float(t) for t in ticks],
        "tick_colors": [hex_color(c) for c in cmap(np.linspace(0.0, 1.0, 5))],
        "reachable": int(reachable.sum()),
        "unreachable": {
            str(r): {
                "color": hex_color(palette[str(r)]),
                "count": int(c),
                "label": _reason_label(str(r)),
                "path": _reason_path(str(r)),
            }
            for r, c in zip(names, counts, strict=True)
        },
    }


def _reason_label(reason: str) -> str:
    return REASON_LABELS.get(reason, reason.replace("_", " "))


def _reason_path(reason: str) -> str:
    return "/grasps/unreachable/" + (_PATH_SAFE.sub("_", reason) or "_")


def grasp_positions(grasps: GraspTable) -> np.ndarray:
    """Positions (N, 3) of the grasp frames in the world [m]."""
    return dq_translation(np.asarray(grasps["dq"], dtype=float))


# -- classes and level of detail ------------------------------------------------------


@dataclass(frozen=True, eq=False)
class GraspClass:
    """One toggleable class of grasps.

    Attributes:
        path: Its scene path (``/grasps/reachable/top``, ...).
        group: ``reachable`` or ``unreachable``.
        label: What the legend calls it.
        color: ``#rrggbb`` of an unreachable reason; None for the reachable
            bands (coloured by manipulability).
        rows: Its table rows, best-ranked first for the reachable bands.
        rgb: ``color`` as RGB in [0, 1] (None with it).
    """

    path: str
    group: str
    label: str
    color: str | None
    rows: np.ndarray
    rgb: tuple[float, float, float] | None = None


def grasp_classes(grasps: GraspTable, top_k: int) -> list[GraspClass]:
    """The table's grasp classes: the two reachable bands, then one per reason (sorted).

    The reachable bands are listed even when empty (a run with no reachable
    grasp says so); an unreachable reason only when it occurs.
    """
    reachable, reason, _ = _classes(grasps)
    rank = column(grasps, "rank", 0).astype(np.int64)
    key = np.where(rank > 0, rank, np.iinfo(np.int64).max)
    rows = np.flatnonzero(reachable)
    rows = rows[np.argsort(key[rows], kind="stable")]
    in_top = (rank[rows] >= 1) & (rank[rows] <= top_k)
    out = [
        GraspClass(
            "/grasps/reachable/top", "reachable", f"reachable, top {top_k}", None, rows[in_top]
        ),
        GraspClass(
            "/grasps/reachable/rest", "reachable", "reachable, other ranks", None, rows[~in_top]
        ),
    ]
    bad = np.flatnonzero(~reachable)
    names, inverse = np.unique(reason[bad], return_inverse=True)
    palette = reason_palette(list(names))
    order = np.argsort(inverse, kind="stable")
    bounds = np.searchsorted(inverse[order], np.arange(len(names) + 1))
    for i, name in enumerate(names.tolist()):
        members = bad[order[bounds[i] : bounds[i + 1]]]
        color = hex_color(palette[name])
        out.append(
            GraspClass(
                _reason_path(name),
                "unreachable",
                f"unreachable: {_reason_label(name)}",
                color,
                members,
                palette[name],
            )
        )
    return out


def _fair_shares(sizes: Sequence[int], budget: int) -> list[int]:
    """Per class, how many of ``budget`` it gets: all when it fits, else an equal share."""
    out = [0] * len(sizes)
    left, todo = max(int(budget), 0), len(sizes)
    for i in sorted(range(len(sizes)), key=lambda j: sizes[j]):
        out[i] = min(int(sizes[i]), left // todo)
        left -= out[i]
        todo -= 1
    return out


def _split(
    classes: Sequence[GraspClass], glyph_budget: int, point_budget: int
) -> list[tuple[np.ndarray, np.ndarray]]:
    """Per class, the rows drawn as glyphs and the rows drawn as dots.

    The top band's glyphs come first; the other classes share what is left
    (the reachable best-ranked first, the unreachable a uniform sample); the
    dots are a uniform sample of each class's other rows.
    """
    rng = np.random.default_rng(0)
    sizes = [len(c.rows) for c in classes]
    n_glyphs = [0] * len(classes)
    left = glyph_budget
    for i, c in enumerate(classes):
        if c.path == "/grasps/reachable/top":
            n_glyphs[i] = min(sizes[i], left)
            left -= n_glyphs[i]
    rest = [i for i, c in enumerate(classes) if c.path != "/grasps/reachable/top"]
    for i, g in zip(rest, _fair_shares([sizes[i] for i in rest], left), strict=True):
        n_glyphs[i] = g
    n_points = _fair_shares([s - g for s, g in zip(sizes, n_glyphs, strict=True)], point_budget)
    out = []
    for c, g, p in zip(classes, n_glyphs, n_points, strict=True):
        if c.group == "reachable":
            glyphs, others = c.rows[:g], c.rows[g:]
        else:
            pick = np.zeros(len(c.rows), dtype=bool)
            pick[rng.choice(len(c.rows), size=g, replace=False)] = True
            glyphs, others = c.rows[pick], c.rows[~pick]
        if p < len(others):
            others = np.sort(others[rng.choice(len(others), size=p, replace=False)])
        out.append((glyphs, others))
    return out


# -- drawing --------------------------------------------------------------------------


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


def points_object(vertices: np.ndarray, colors: np.ndarray, size: float) -> Any:
    """One meshcat ``Points`` object: positions (M, 3), colours (M, 3) in [0, 1], edge [m]."""
    mg = load_meshcat().geometry
    geometry = mg.PointsGeometry(
        np.ascontiguousarray(vertices.T, dtype=np.float32),
        np.ascontiguousarray(colors.T, dtype=np.float32),
    )
    return mg.Points(geometry, mg.PointsMaterial(size=float(size)))


@dataclass(frozen=True)
class GraspDrawing:
    """What :func:`draw_grasps` drew.

    Attributes:
        layers: One layer dict per class (see :class:`~.scene.SceneInfo`).
        lod: ``{"glyph_budget", "point_budget", "glyphs", "points",
            "classes": {path: {"count", "glyphs", "points"}}}``: grasps drawn
            as glyphs and as dots, in all and per class.
        n_reachable: Reachable grasps in the table.
        n_unreachable: Unreachable grasps in the table.
    """

    layers: list[dict[str, Any]]
    lod: dict[str, Any]
    n_reachable: int
    n_unreachable: int


def _row_colors(grasps: GraspTable, cls: GraspClass, rows: np.ndarray, vrange: Any) -> np.ndarray:
    """Colours (M, 3) float32 of ``rows`` of class ``cls``."""
    if cls.rgb is not None:
        return np.tile(np.asarray(cls.rgb, dtype=np.float32), (len(rows), 1))
    vmin, vmax = vrange
    if "manipulability" in grasps:
        m = np.asarray(grasps["manipulability"], dtype=float)[rows]
    else:
        m = np.full(len(rows), np.nan)
    t = np.clip((np.where(np.isfinite(m), m, vmin) - vmin) / (vmax - vmin), 0.0, 1.0)
    return colormap(_COLORMAP)(t)[:, :3].astype(np.float32)


def draw_grasps(
    vis: Any,
    grasps: GraspTable,
    positions: np.ndarray,
    glyph: GripperGlyph,
    top_k: int,
    glyph_budget: int = GLYPH_BUDGET,
    point_budget: int = POINT_BUDGET,
) -> GraspDrawing:
    """Draw each grasp class at its path: glyphs of ``glyph``, the rest as dots.

    Args:
        vis: The meshcat visualizer.
        grasps: The grasp table (``dq``; ``reachable``, ``reason``,
            ``manipulability``, ``rank`` when present).
        positions: The grasp frames' positions (N, 3) in the world [m].
        glyph: The gripper outline.
        top_k: Ranks ``1 .. top_k`` make the top band.
        glyph_budget: Most glyphs over all classes.
        point_budget: Most dots over all classes.
    """
    reachable, _, manip = _classes(grasps)
    vrange = _manipulability_range(manip[reachable])
    template = glyph.template()
    dq = np.asarray(grasps["dq"], dtype=float)
    classes = grasp_classes(grasps, top_k)
    layers: list[dict[str, Any]] = []
    per_class: dict[str, dict[str, int]] = {}
    for cls, (g_rows, p_rows) in zip(
        classes, _split(classes, glyph_budget, point_budget), strict=True
    ):
        if len(g_rows):
            rot = dq_to_matrix(dq[g_rows])[:, :3, :3]
            verts = _glyph_segments(rot, positions[g_rows], template)
            colors = np.repeat(_row_colors(grasps, cls, g_rows, vrange), len(template), axis=0)
            width = 2.0 if cls.group == "reachable" else 1.0
            vis[cls.path.lstrip("/") + "/glyphs"].set_object(line_segments(verts, colors, width))
        if len(p_rows):
            colors = _row_colors(grasps, cls, p_rows, vrange)
            obj = points_object(positions[p_rows], colors, POINT_SIZE)
            vis[cls.path.lstrip("/") + "/points"].set_object(obj)
        count = len(cls.rows)
        per_class[cls.path] = {"count": count, "glyphs": len(g_rows), "points": len(p_rows)}
        layers.append(
            {
                "path": cls.path,
                "group": cls.group,
                "label": cls.label,
                "color": cls.color,
                "count": count,
                "visible": True,
            }
        )
    lod = {
        "glyph_budget": int(glyph_budget),
        "point_budget": int(point_budget),
        "glyphs": sum(v["glyphs"] for v in per_class.values()),
        "points": sum(v["points"] for v in per_class.values()),
        "classes": per_class,
    }
    return GraspDrawing(layers, lod, int(reachable.sum()), int((~reachable).sum()))
