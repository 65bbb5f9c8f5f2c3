"""PNG plots of a run: the manifold chart, coverage, the manipulability histogram, counts.

Each plot has a function returning its figure (``manifold_figure``,
``patches_figure``, ``levels_figure``, ``hist_figure``, ``counts_figure``) and
:func:`write_plots` saves them. ``counts.png`` shows the stages in pipeline
order on a linear scale with the unreachable grasps stacked by reason; the
chart plots are fitted to their data and mark the robot side
(:func:`~gcm_pipeline.outputs.chart_marks.robot_side`) when given the robot's base pose.

Figures are drawn with matplotlib's object API on the Agg canvas (no pyplot,
no global backend switch), so plotting works headless and from threads.
"""

from __future__ import annotations

import os
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from gcm_pipeline.errors import OutputError, PublishError
from gcm_pipeline.geometry.dualquat import dq_translation
from gcm_pipeline.outputs.chart_marks import (
    ROBOT_SIDE_COLOR,
    approach_from_base,
    fit_limits,
    mark_robot_side,
    robot_side,
)
from gcm_pipeline.outputs.pose_view import PoseView, equal_axes
from gcm_pipeline.rundir.transaction import atomic_file
from gcm_pipeline.table import GraspTable

__all__ = [
    "COVERAGE_FILE",
    "PLOT_FILES",
    "REASON_COLORS",
    "StageBar",
    "candidate_coverage",
    "candidate_rows",
    "chart_axis_labels",
    "chart_period",
    "chart_points",
    "colormap",
    "counts_figure",
    "hist_figure",
    "levels_figure",
    "manifold_figure",
    "patch_sizes",
    "patches_figure",
    "plot_coverage",
    "reason_palette",
    "stage_bars",
    "unreachable_reasons",
    "write_plots",
]

#: The coverage figure (:func:`plot_coverage`), written for a manifold with ``isolation``.
COVERAGE_FILE = "coverage.png"
#: File names written by :func:`write_plots`, in order.
PLOT_FILES = ("manifold.png", "manipulability_hist.png", "counts.png")

#: Colour [r, g, b] in [0, 1] of unreachable grasps by ``reason``; other reasons
#: take the next colour of a small extra palette in sorted order. Greys, reds,
#: pinks and browns: hues and lightnesses that viridis (dark purple, blue, teal,
#: green, yellow) never takes, so a reason never reads as a metric value, and no
#: orange beside viridis' yellow.
REASON_COLORS: dict[str, tuple[float, float, float]] = {
    "out_of_reach": (0.82, 0.82, 0.82),
    "no_ik": (0.58, 0.58, 0.58),
    "joint_limits": (0.33, 0.33, 0.33),
    "collision_self": (0.84, 0.11, 0.16),
    "collision_environment": (0.55, 0.34, 0.27),
    "collision_object": (0.97, 0.55, 0.78),
    "approach": (0.55, 0.04, 0.27),
    "retreat": (0.78, 0.58, 0.55),
    "unchecked": (1.00, 1.00, 1.00),
}
_EXTRA_REASON_COLORS = (
    (0.40, 0.00, 0.00),
    (0.75, 0.00, 0.45),
    (0.10, 0.10, 0.10),
    (0.93, 0.38, 0.45),
    (0.70, 0.20, 0.55),
)


def reason_palette(reasons: Sequence[str]) -> dict[str, tuple[float, float, float]]:
    """Colour of each distinct reason: :data:`REASON_COLORS`, else the extra palette.

    Args:
        reasons: Reasons (repeats allowed).

    Returns:
        Reason -> (r, g, b) in [0, 1], in sorted reason order.
    """
    names = sorted({str(r) for r in reasons})
    extra = list(_EXTRA_REASON_COLORS)
    out: dict[str, tuple[float, float, float]] = {}
    i = 0
    for reason in names:
        if reason in REASON_COLORS:
            out[reason] = REASON_COLORS[reason]
        else:
            out[reason] = extra[i % len(extra)]
            i += 1
    return out


_DPI = 110
_AXIS_NAMES = {
    "xy": ("world x", "world y"),
    "pca": ("first principal axis", "second principal axis"),
    "cylindrical": ("arc length R·θ", "height along the axis"),
    "spherical": ("stereographic u", "stereographic v"),
}
_PATCH_LABELS = 8  # patches named in the legend (the largest; ids are by size)
_MANIP_LABEL = "manipulability: Yoshikawa index √det(J Jᵀ)"
_RINGS = 300  # candidates ringed in the world view up to this many
_COUNT_ORDER = ("candidates", "triangles", "triangles_dropped", "densified", "reachable")


def colormap(name: str) -> Any:
    """A matplotlib colormap by name (matplotlib, imported by this module, loads on first use)."""
    from matplotlib import colormaps

    return colormaps[name]


def _figure(size: tuple[float, float] = (6.4, 4.8)) -> Any:
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=size, dpi=_DPI, layout="constrained")
    FigureCanvasAgg(fig)
    return fig


def _save(fig: Any, path: Path) -> Path:
    """Write ``fig`` as the PNG ``path``, whole or not at all (a temporary sibling renamed)."""
    try:
        with atomic_file(path) as tmp:
            fig.savefig(tmp, dpi=_DPI, format="png")
    except (OSError, OutputError) as exc:
        raise PublishError(f"cannot write plot {str(path)!r}: {exc}") from exc
    return path


def chart_axis_labels(projection: str | None) -> tuple[str, str]:
    """Axis labels (u, v) of a chart plot; the stereographic ones have no unit."""
    u_name, v_name = _AXIS_NAMES.get(projection or "", ("chart u", "chart v"))
    unit = "" if projection == "spherical" else " [m]"
    return f"{u_name}{unit}", f"{v_name}{unit}"


def chart_period(grasps: GraspTable, manifold: Any) -> float | None:
    """Period [m] of the chart's u axis (``2 pi R`` for ``cylindrical``), else None.

    The manifold's own ``period`` when it has one. Otherwise (a manifold-like
    object without it) ``2 pi r`` with ``r`` the candidates' median distance
    from the axis of ``manifold.frame``.
    """
    frame = getattr(manifold, "frame", None)
    if getattr(manifold, "projection", None) != "cylindrical" or frame is None:
        return None
    period = getattr(manifold, "period", None)
    if period is not None:
        return float(period)
    if "dq" not in grasps:
        return None
    rows = candidate_rows(grasps, len(manifold.chart))
    pos = np.asarray(dq_translation(np.asarray(grasps["dq"])[rows]), dtype=float)
    frame = np.asarray(frame, dtype=float)
    local = (pos - frame[:3, 3]) @ frame[:3, :3]
    radius = float(np.median(np.hypot(local[:, 0], local[:, 1]))) if len(local) else 0.0
    return 2.0 * np.pi * radius if radius > 0 else None


def candidate_rows(grasps: GraspTable, n_chart: int) -> np.ndarray:
    """Table rows of the manifold's vertices (candidate ids ``0 .. n_chart - 1``).

    The candidates come first in a densified table (``origin`` ``candidate``);
    a table without ``origin`` is the candidate table itself.
    """
    origin = grasps.get("origin")
    if origin is None:
        return np.arange(min(len(grasps), n_chart))
    return np.flatnonzero(np.asarray(origin).astype(str) == "candidate")[:n_chart]


def _unwrap(corners: np.ndarray, period: float | None) -> np.ndarray:
    """Shift u of corners (..., 3, 2) by whole periods to lie within half a period of corner 0."""
    if period is None:
        return corners
    out = corners.copy()
    du = out[..., :, 0] - out[..., :1, 0]
    out[..., :, 0] -= period * np.round(du / period)
    return out


def chart_points(grasps: GraspTable, manifold: Any, period: float | None = None) -> np.ndarray:
    """Chart coordinates (N, 2) of every grasp row.

    Candidate rows take their own chart coordinates (``manifold.chart``, in
    candidate order); interpolated rows the barycentric blend
    ``sum_k weights[k] * chart[vertices[k]]`` of their triangle's corners
    (unwrapped across the seam of a periodic chart of u-period ``period``).
    Rows that cannot be placed are NaN.

    Args:
        grasps: The table (``origin``, ``vertices``, ``weights`` used when present).
        manifold: Object with ``chart`` (Nc, 2).
        period: Period of the chart's u axis [m] (see :func:`chart_period`) or None.

    Returns:
        (N, 2) float array.
    """
    chart = np.asarray(manifold.chart, dtype=float)
    n = len(grasps)
    out = np.full((n, 2), np.nan)
    rows = candidate_rows(grasps, len(chart))
    out[rows] = chart[: len(rows)]
    origin = grasps.get("origin")
    if "vertices" in grasps and "weights" in grasps:
        verts = np.asarray(grasps["vertices"], dtype=np.int64)
        w = np.asarray(grasps["weights"], dtype=float)
        ok = np.all((verts >= 0) & (verts < len(chart)), axis=1) & np.all(np.isfinite(w), axis=1)
        if origin is not None:
            ok &= np.asarray(origin).astype(str) != "candidate"
        corners = _unwrap(chart[verts[ok]], period)
        out[ok] = np.einsum("nk,nkd->nd", w[ok], corners)
    return out


def _chart_figure(grasps: GraspTable, manifold: Any) -> tuple[Any, Any, np.ndarray, np.ndarray]:
    """A figure with the manifold's triangles drawn in its chart.

    Returns:
        ``(fig, ax, pts, corners)``: ``pts`` (N, 2) the chart coordinates of
        every row (NaN where a row cannot be placed), ``corners`` (T, 3, 2) the
        triangles' corners (unwrapped across a periodic seam).
    """
    fig = _figure((7.0, 6.0))
    ax = fig.add_subplot()
    chart = np.asarray(getattr(manifold, "chart", np.empty((0, 2))), dtype=float)
    tris = np.asarray(getattr(manifold, "triangles", np.empty((0, 3))), dtype=np.int64)
    period = chart_period(grasps, manifold) if len(chart) else None
    corners = np.empty((0, 3, 2))
    if len(chart) and len(tris):
        from matplotlib.collections import PolyCollection

        corners = _unwrap(chart[tris.reshape(-1, 3)], period)
        ax.add_collection(
            PolyCollection(
                list(corners),
                facecolors="none",
                edgecolors="0.55",
                linewidths=0.7,
                zorder=1,
                label=f"triangles ({len(tris)})",
            )
        )
    pts = (
        chart_points(grasps, manifold, period) if len(chart) else np.full((len(grasps), 2), np.nan)
    )
    return fig, ax, pts, corners


class _ChartView:
    """The one 2-D chart of the ``chart`` structure, with the interface of :class:`PoseView`.

    Its axes are fitted to the rows and triangles drawn and the robot side
    marked when ``base_pose`` is given (:mod:`gcm_pipeline.outputs.chart_marks`).
    """

    def __init__(self, grasps: GraspTable, manifold: Any, base_pose: Any = None) -> None:
        self.fig, self.ax, self.pts, self.corners = _chart_figure(grasps, manifold)
        self.projection = str(getattr(manifold, "projection", "") or "")
        self.placed = np.all(np.isfinite(self.pts), axis=1)
        self.colorbar_axes = self.legend_axes = self.ax
        self.period = chart_period(grasps, manifold) if len(self.pts) and manifold else None
        self.side = None if manifold is None else robot_side(manifold, base_pose)

    def scatter(self, sel: np.ndarray, *, label: str | None = None, **kw: Any) -> Any:
        sel = sel & self.placed
        return self.ax.scatter(self.pts[sel, 0], self.pts[sel, 1], label=label, **kw)

    def finish(self, title: str) -> None:
        """Fit the limits, mark the robot side, label the axes, the legend below."""
        ax = self.ax
        to_scale, *box = fit_limits(
            ax, np.vstack((self.pts[self.placed], self.corners.reshape(-1, 2)))
        )
        if self.side is not None:
            mark_robot_side(ax, self.side, self.period)
        u_label, v_label = chart_axis_labels(self.projection)
        ax.set_xlabel(u_label)
        ax.set_ylabel(v_label)
        head, _, tail = title.partition("\n")  # the projection goes on the first line
        lines = [f"{head} ({self.projection} projection)" if self.projection else head]
        lines += [tail] if tail else []
        if not to_scale:
            lines[-1] += "; axes not to scale" if tail else "\naxes not to scale"
        pad = 16.0 if self.side is not None and self.side.kind == "u" else 6.0  # "robot side"
        ax.set_title("\n".join(lines), fontsize="medium", pad=pad)
        entries = len(ax.get_legend_handles_labels()[0])
        if entries:
            legend = ax.legend(
                loc="upper center",
                bbox_to_anchor=(0.5, -0.13),
                ncols=2,
                fontsize="small",
                frameon=False,
            )
            for handle in legend.legend_handles:
                if hasattr(handle, "set_sizes"):
                    handle.set_sizes([24.0])
        ax.grid(alpha=0.25)
        self.fig.set_size_inches(box[0] + 2.2, box[1] + 1.5 + 0.19 * ((entries + 1) // 2))


def _view(grasps: GraspTable, manifold: Any, what: str, base_pose: Any = None) -> tuple[Any, str]:
    """The view to draw on and the title's suffix for the manifold's structure.

    The ``families`` structure is drawn in the world (:class:`PoseView`), the
    ``chart`` structure in its chart (with the robot side from ``base_pose``).
    """
    if getattr(manifold, "structure", "chart") != "families" or "dq" not in grasps:
        return _ChartView(grasps, manifold, base_pose), what
    view = PoseView(
        _figure((12.0, 5.8)), grasps, manifold, candidate_rows(grasps, len(manifold.chart))
    )
    azimuth = approach_from_base(grasps, base_pose)
    if azimuth is not None:
        style = {"color": ROBOT_SIDE_COLOR, "linestyle": "--", "linewidth": 1.2}
        view.directions.axvline(azimuth, **style)
        # a proxy on the axes whose handles make the figure's legend
        view.legend_axes.plot([], [], label="approach from the robot side", **style)
    family = getattr(manifold, "family", None)
    if family is None:  # a manifold.npz without it: no count to give
        return view, f"{what}, {len(manifold.triangles)} triangles"
    fams = int(np.max(family, initial=-1)) + 1
    return view, f"{what}, {len(manifold.triangles)} triangles in {fams} families"


def _marker_size(grasps: GraspTable, smallest: float = 2.0) -> float:
    return float(np.clip(3000.0 / max(len(grasps), 1), smallest, 30.0))


def levels_figure(grasps: GraspTable, manifold: Any, base_pose: Any = None) -> Any:
    """``levels.png``: adaptive refinement, rows coloured by level, unreachable as crosses."""
    view, suffix = _view(grasps, manifold, "", base_pose)
    level = np.asarray(grasps["level"], dtype=np.int64)
    reach = np.asarray(grasps.get("reachable", np.ones(len(grasps), bool)), dtype=bool)
    size = _marker_size(grasps)
    cmap = colormap("plasma")
    top = max(int(level.max(initial=0)), 1)
    for lv in range(int(level.max(initial=-1)) + 1):
        colour = cmap(0.85 * lv / top)
        for ok, marker in ((True, "o"), (False, "x")):
            sel = _placed(view, (level == lv) & (reach == ok))
            if not sel.any():
                continue
            label = f"level {lv}, {'reachable' if ok else 'unreachable'} ({int(sel.sum())})"
            view.scatter(
                sel,
                s=size if ok else size * 1.3,
                marker=marker,
                color=colour,
                linewidths=0.8,
                edgecolors="none" if ok else None,
                label=label,
                zorder=2 + lv,
                rasterized=len(grasps) > 5000,
            )
    title = f"Adaptive refinement: {len(grasps):,} grasps, levels 0..{int(level.max(initial=0))}"
    view.finish(title + suffix)
    return view.fig


#: Colours of the named patches: matplotlib's tab10 without its grey, which marks the rest.
_PATCH_COLORS = tuple(i for i in range(10) if i != 7)


def _plural(n: int, word: str) -> str:
    """``"1 grasp"``, ``"1,044 grasps"``, ``"2 patches"``."""
    return f"{n:,} {word}" if n == 1 else f"{n:,} {word}{'es' if word.endswith('ch') else 's'}"


def patch_sizes(grasps: GraspTable) -> list[tuple[int, int]]:
    """``(patch id, grasps)`` of every patch, largest first (ties by id)."""
    patch = np.asarray(grasps["patch"], dtype=np.int64)
    ids, counts = np.unique(patch[patch >= 0], return_counts=True)
    return sorted(zip(ids.tolist(), counts.tolist(), strict=True), key=lambda p: (-p[1], p[0]))


def patches_figure(grasps: GraspTable, manifold: Any, base_pose: Any = None) -> Any:
    """``patches.png``: reachable rows coloured by IK patch (one branch each).

    The :data:`_PATCH_LABELS` largest patches each get their own colour and a
    legend entry ``patch <id>: <n> grasps``; the others share one grey and one
    entry; the title says how many patches there are and which are coloured.
    """
    view, suffix = _view(grasps, manifold, "", base_pose)
    patch = np.asarray(grasps["patch"], dtype=np.int64)
    size = _marker_size(grasps)
    tab = colormap("tab10")
    sizes = patch_sizes(grasps)
    named, rest = sizes[:_PATCH_LABELS], sizes[_PATCH_LABELS:]
    raster = len(grasps) > 5000
    for k, (pid, n) in enumerate(named):
        colour = tab(_PATCH_COLORS[k % len(_PATCH_COLORS)])
        label = f"patch {pid}: {_plural(n, 'grasp')}"
        view.scatter(
            patch == pid,
            s=size,
            color=colour,
            edgecolors="none",
            label=label,
            zorder=3,
            rasterized=raster,
        )
    title = f"IK patches (branches): {_plural(len(sizes), 'patch')}"
    if rest:
        others = np.isin(patch, [pid for pid, _ in rest])
        n_rest = int(others.sum())
        view.scatter(
            others,
            s=size,
            color="0.45",
            edgecolors="none",
            zorder=3,
            rasterized=raster,
            label=f"other {_plural(len(rest), 'patch')}: {_plural(n_rest, 'grasp')}",
        )
        title += (
            f"\nthe {len(named)} largest coloured, the other {len(rest)} "
            f"({_plural(n_rest, 'grasp')}) grey"
        )
    bad = patch < 0
    if bad.any():
        view.scatter(
            bad,
            s=size,
            marker="x",
            color="0.78",
            linewidths=0.6,
            label=f"unreachable: {_plural(int(bad.sum()), 'grasp')}",
            zorder=2,
            rasterized=raster,
        )
    view.finish(title + suffix)
    return view.fig


def manifold_figure(grasps: GraspTable, manifold: Any, base_pose: Any = None) -> Any:
    """``manifold.png``: reachable rows by manipulability, unreachable by reason, candidates ringed.

    The candidates are ringed in the chart view, and in the world view up to
    a few hundred of them (beyond, ``coverage.png`` shows them).
    """
    view, suffix = _view(grasps, manifold, "", base_pose)
    chart = np.asarray(getattr(manifold, "chart", np.empty((0, 2))), dtype=float)
    reach = np.asarray(grasps.get("reachable", np.zeros(len(grasps), bool)), dtype=bool)
    manip = np.asarray(grasps.get("manipulability", np.full(len(grasps), np.nan)), dtype=float)
    size = _marker_size(grasps, 1.0)
    bad = ~reach
    reasons = np.asarray(grasps.get("reason", np.full(len(grasps), "no_ik"))).astype(str)
    reasons = np.where(reasons == "", "no_ik", reasons)
    for reason, rgb in reason_palette(reasons[_placed(view, bad)]).items():
        sel = _placed(view, bad & (reasons == reason))
        view.scatter(
            sel,
            s=size,
            marker="x",
            color=rgb,
            linewidths=0.8,
            label=f"unreachable: {reason} ({int(sel.sum())})",
            zorder=2,
            rasterized=len(grasps) > 5000,
        )
    good = _placed(view, reach & np.isfinite(manip))
    if good.any():
        sc = view.scatter(
            good,
            s=size,
            c=manip[good],
            cmap="viridis",
            label=f"reachable ({int(good.sum())})",
            zorder=3,
            rasterized=len(grasps) > 5000,
            edgecolors="none",
        )
        view.fig.colorbar(sc, ax=view.colorbar_axes, label=_MANIP_LABEL)
    cand = np.asarray(grasps.get("origin", np.array([], dtype=str))).astype(str) == "candidate"
    if cand.any() and len(chart) and (isinstance(view, _ChartView) or cand.sum() <= _RINGS):
        view.scatter(
            cand,
            s=28,
            facecolors="none",
            edgecolors="crimson",
            linewidths=1.0,
            label="candidates",
            zorder=4,
        )
    title = "Grasp manifold in its 2-D chart" if isinstance(view, _ChartView) else "Grasp manifold"
    view.finish(title + suffix)
    return view.fig


def _placed(view: Any, sel: np.ndarray) -> np.ndarray:
    """``sel`` restricted to the rows the view can place (all rows in the world view)."""
    placed = getattr(view, "placed", None)
    return sel if placed is None else sel & placed


def hist_figure(grasps: GraspTable) -> Any:
    """``manipulability_hist.png``: the reachable grasps' manipulability, binned.

    The bars take the colour of their values in ``manifold.png``'s colour
    bar (viridis over the same range); the median is marked.
    """
    fig = _figure()
    ax = fig.add_subplot()
    reach = np.asarray(grasps.get("reachable", np.zeros(len(grasps), bool)), dtype=bool)
    manip = np.asarray(grasps.get("manipulability", np.full(len(grasps), np.nan)), dtype=float)
    values = manip[reach & np.isfinite(manip)]
    if values.size:
        bins = int(np.clip(np.sqrt(values.size), 10, 60))
        _, edges, patches = ax.hist(values, bins=bins, edgecolor="white", linewidth=0.4)
        cmap = colormap("viridis")
        lo, hi = float(values.min()), float(values.max())
        span = hi - lo if hi > lo else 1.0
        for left, right, patch in zip(edges[:-1], edges[1:], patches, strict=True):
            patch.set_facecolor(cmap((0.5 * (left + right) - lo) / span))
        ax.axvline(
            float(np.median(values)),
            color="crimson",
            linewidth=1.2,
            label=f"median {np.median(values):.4g}",
        )
        ax.legend(fontsize="small")
    else:
        ax.text(0.5, 0.5, "no reachable grasp", ha="center", va="center", transform=ax.transAxes)
    ax.set_xlabel(_MANIP_LABEL)
    ax.set_ylabel("reachable grasps per bin")
    ax.set_title(f"Manipulability of the reachable grasps: {values.size:,} of {len(grasps):,}")
    ax.grid(alpha=0.25, axis="y")
    ax.set_axisbelow(True)
    return fig


@dataclass(frozen=True)
class StageBar:
    """One bar of ``counts.png``: its segments from the bottom up and the note above it.

    Attributes:
        key: The stage (``candidates``, ``triangles``, ``densified``,
            ``unreachable``, ``reachable``, ``top``).
        label: Tick label.
        segments: ``(name, count, colour)`` from the bottom up; ``colour``
            (r, g, b) in [0, 1].
        note: Text above the bar (the total, and its share of the densified grasps).
    """

    key: str
    label: str
    segments: tuple[tuple[str, int, tuple[float, float, float]], ...]
    note: str

    @property
    def total(self) -> int:
        """Height of the bar: the sum of its segments."""
        return sum(n for _, n, _ in self.segments)


_STAGE_COLORS = {
    "candidates": (0.29, 0.56, 0.85),
    "triangles": (0.50, 0.50, 0.50),
    "triangles_dropped": (0.80, 0.80, 0.80),
    "densified": (0.35, 0.64, 0.41),
    "reachable": (0.13, 0.57, 0.55),  # viridis' middle: the colour of a metric, not a reason
    "top": (0.99, 0.91, 0.14),
    "unreachable": (0.62, 0.62, 0.62),
}


def _share(n: int, of: int | None) -> str:
    """``"1,044"`` or ``"659 (63 %)"`` of ``of``."""
    return f"{n:,}" if not of else f"{n:,} ({100.0 * n / of:.0f} %)"


def unreachable_reasons(
    grasps: GraspTable | None, counts: Mapping[str, int]
) -> dict[str, int] | None:
    """Unreachable grasps by reason, most first; None if the table does not give them.

    From the table's ``reachable`` and ``reason`` columns (an empty reason is
    ``unknown``), when the table is the one ``counts`` describes (its length is
    ``counts["densified"]`` and its reachable rows ``counts["reachable"]``).
    """
    if grasps is None or "reachable" not in grasps or "reason" not in grasps:
        return None
    reach = np.asarray(grasps["reachable"], dtype=bool)
    if counts.get("densified", len(reach)) != len(reach):
        return None
    if counts.get("reachable", int(reach.sum())) != int(reach.sum()):
        return None
    reasons = np.asarray(grasps["reason"]).astype(str)[~reach]
    names, n = np.unique(np.where(reasons == "", "unknown", reasons), return_counts=True)
    pairs = sorted(zip(names.tolist(), n.tolist(), strict=True), key=lambda p: (-p[1], p[0]))
    return {str(k): int(v) for k, v in pairs}


def stage_bars(counts: Mapping[str, int], grasps: GraspTable | None = None) -> list[StageBar]:
    """The bars of ``counts.png`` in pipeline order (the stages ``counts`` has).

    candidates -> manifold triangles (kept, then dropped) -> densified grasps ->
    unreachable (one segment per reason, most frequent at the bottom) ->
    reachable -> top-k. The unreachable, reachable and top-k notes give their
    share of the densified grasps. ``counts["top"]`` or else the table's ``top``
    column gives the top-k bar.

    Args:
        counts: Per-stage counts (``summary["counts"]``' whole numbers).
        grasps: The table the counts describe (its reasons), or None.
    """
    c = _STAGE_COLORS
    bars: list[StageBar] = []
    if "candidates" in counts:
        n = int(counts["candidates"])
        bars.append(
            StageBar("candidates", "candidates", (("candidates", n, c["candidates"]),), f"{n:,}")
        )
    if "triangles" in counts:
        kept, dropped = int(counts["triangles"]), int(counts.get("triangles_dropped", 0))
        segs = [("kept", kept, c["triangles"])]
        if dropped:
            segs.append(("dropped", dropped, c["triangles_dropped"]))
        note = f"{kept:,}" + (f" (+{dropped:,} dropped)" if dropped else "")
        bars.append(StageBar("triangles", "manifold\ntriangles", tuple(segs), note))
    total = int(counts["densified"]) if "densified" in counts else None
    if total is not None:
        bars.append(
            StageBar(
                "densified",
                "densified\ngrasps",
                (("densified", total, c["densified"]),),
                f"{total:,}",
            )
        )
    if "reachable" in counts:
        reachable = int(counts["reachable"])
        if total is not None:
            reasons = unreachable_reasons(grasps, counts) or (
                {"unknown": total - reachable} if total > reachable else {}
            )
            palette = reason_palette(list(reasons))
            palette.update({"unknown": c["unreachable"]} if "unknown" in reasons else {})
            segs = tuple((r, n, palette[r]) for r, n in reasons.items())
            bars.append(
                StageBar(
                    "unreachable",
                    "unreachable\n(by reason)",
                    segs,
                    _share(sum(reasons.values()), total),
                )
            )
        bars.append(
            StageBar(
                "reachable",
                "reachable",
                (("reachable", reachable, c["reachable"]),),
                _share(reachable, total),
            )
        )
    top = counts.get("top")
    if top is None and grasps is not None and "top" in grasps:
        top = int(np.count_nonzero(grasps["top"]))
    if top:
        bars.append(
            StageBar(
                "top", "top-k\n(ranked)", (("top", int(top), c["top"]),), _share(int(top), total)
            )
        )
    return bars


def counts_figure(counts: Mapping[str, int], grasps: GraspTable | None = None) -> Any:
    """The figure of ``counts.png``: :func:`stage_bars` on a linear scale.

    One bar container per segment (its ``gid`` ``"<stage>:<segment>"``; the
    unreachable bar's segments labelled ``"<reason>: <count>"`` for the
    legend), the notes above the bars, the counts of the reasons inside their
    segments when they fit; the dropped triangles hatched.

    Returns:
        The matplotlib figure (one axes).
    """
    fig = _figure((7.4, 4.8))
    ax = fig.add_subplot()
    bars = stage_bars(counts, grasps)
    top = max((b.total for b in bars), default=0)
    for i, bar in enumerate(bars):
        bottom = 0
        for name, n, colour in bar.segments:
            reason = bar.key == "unreachable"
            cont = ax.bar(
                [i],
                [n],
                bottom=[bottom],
                color=[colour],
                edgecolor="white",
                linewidth=0.6,
                hatch="///" if name == "dropped" else None,
                label=f"{name}: {n:,}" if reason else None,
                gid=f"{bar.key}:{name}",
            )
            if reason and n >= 0.045 * top:
                ax.bar_label(cont, labels=[f"{n:,}"], label_type="center", fontsize="x-small")
            bottom += n
        ax.text(i, bar.total, bar.note, ha="center", va="bottom", fontsize="small")
    ax.set_xticks(range(len(bars)), [b.label for b in bars])
    ax.set_yscale("linear")
    ax.set_ylim(0, max(top, 1) * 1.12)
    ax.set_ylabel("count (grasps; triangles for the manifold)")
    by_key = {b.key: b for b in bars}
    title = "Per-stage counts"
    if "reachable" in by_key and "densified" in by_key:
        n, of = by_key["reachable"].total, by_key["densified"].total
        title += f": {n:,} of {of:,} grasps reachable" + (
            f" ({100.0 * n / of:.0f} %)" if of else ""
        )
    ax.set_title(title)
    if ax.get_legend_handles_labels()[0]:
        handles, labels = ax.get_legend_handles_labels()
        ax.legend(
            handles[::-1],
            labels[::-1],
            fontsize="x-small",
            loc="best",
            title="unreachable, by reason",
            title_fontsize="x-small",
        )
    ax.grid(alpha=0.25, axis="y")
    ax.set_axisbelow(True)
    return fig


# --------------------------------------------------------------------------- coverage
_COVERAGE_COLORS = {
    "linked": (0.13, 0.55, 0.13),
    "no_neighbour": (0.85, 0.10, 0.10),
    "no_triple": (1.00, 0.55, 0.00),
    "duplicate": (0.45, 0.45, 0.45),
    "unused": (0.85, 0.10, 0.10),
}


def candidate_coverage(manifold: Any) -> np.ndarray:
    """(N,) per candidate ``linked`` or why it is in no triangle."""
    n = len(manifold.chart)
    used = np.zeros(n, dtype=bool)
    used[np.asarray(manifold.triangles, dtype=np.int64).ravel()] = True
    isolation = getattr(manifold, "isolation", None)
    out = np.where(used, "linked", "unused").astype("<U12")
    if isolation is not None:
        iso = np.asarray(isolation).astype(str)
        out[~used] = np.where(iso[~used] == "", "unused", iso[~used])
    return out


def plot_coverage(grasps: GraspTable, manifold: Any, path: Path) -> Path:
    """Write the coverage figure (see the module docstring) to ``path``."""
    n = len(manifold.chart)
    rows = candidate_rows(grasps, n)
    pos = dq_translation(np.asarray(grasps["dq"], dtype=np.float64)[rows])
    tris = np.asarray(manifold.triangles, dtype=np.int64).reshape(-1, 3)
    fig = _figure((12.0, 5.6))
    left = fig.add_subplot(1, 2, 1, projection="3d")
    right = fig.add_subplot(1, 2, 2, projection="3d")
    if len(tris):
        from mpl_toolkits.mplot3d.art3d import Line3DCollection

        seg = pos[tris[:, [0, 1, 1, 2, 2, 0]]].reshape(-1, 2, 3)
        left.add_collection3d(Line3DCollection(seg, colors="0.6", linewidths=0.3, alpha=0.6))
    if "reachable" in grasps:
        ok = np.asarray(grasps["reachable"], dtype=bool)[rows]
        for mask, color, label in ((ok, "#2ca02c", "reachable"), (~ok, "0.55", "unreachable")):
            left.scatter(*pos[mask].T, s=6, color=color, label=f"{label} ({mask.sum()})")
    else:
        left.scatter(*pos.T, s=6, color="k", label=f"candidates ({n})")
    left.set_title(f"Manifold: {len(tris)} triangles on {n} candidates")
    cover = candidate_coverage(manifold)
    for reason in sorted(set(cover.tolist()), key=lambda r: (r != "linked", r)):
        mask = cover == reason
        right.scatter(
            *pos[mask].T,
            s=6 if reason == "linked" else 18,
            color=_COVERAGE_COLORS.get(reason, (0.2, 0.2, 0.8)),
            label=f"{reason} ({mask.sum()})",
        )
    structure = getattr(manifold, "structure", "chart")
    right.set_title(f"Coverage ({structure} structure): linked and isolated candidates")
    for ax in (left, right):
        ax.set_xlabel("x [m]")
        ax.set_ylabel("y [m]")
        ax.set_zlabel("z [m]")
        equal_axes(ax, pos)
        ax.legend(loc="upper left", fontsize=8)
    return _save(fig, path)


def write_plots(
    grasps: GraspTable,
    manifold: Any,
    counts: Mapping[str, int],
    out_dir: str | os.PathLike[str],
    base_pose: Any = None,
) -> list[Path]:
    """Write ``manifold.png``, ``manipulability_hist.png`` and ``counts.png`` (and more).

    A table with a ``level`` column (adaptive densification) also gets
    ``levels.png``, one with a ``patch`` column (IK continuity) and a reachable
    grasp ``patches.png``, a manifold of the families structure (``isolation``)
    ``coverage.png`` (:func:`plot_coverage`).

    Args:
        grasps: The grasp table (``reachable``, ``manipulability``, ``origin``,
            ``vertices``, ``weights`` used when present).
        manifold: Object with ``chart`` (Nc, 2), ``triangles`` (T, 3) and
            optionally ``projection``; None gives an empty chart plot.
        counts: Per-stage counts, e.g. ``summary["counts"]``
            (``candidates``, ``triangles``, ``triangles_dropped``, ``densified``,
            ``reachable``; other keys are plotted after these).
        out_dir: An existing directory.
        base_pose: The robot base in the world (4, 4) [m]: the chart plots mark
            the robot side (:func:`~gcm_pipeline.outputs.chart_marks.robot_side`); None: not marked.

    Returns:
        The paths: the three of :data:`PLOT_FILES`, then ``levels.png``,
        ``patches.png`` and ``coverage.png`` when written.

    Raises:
        PublishError: ``out_dir`` is not a directory or a file cannot be written.
    """
    out = Path(out_dir)
    if not out.is_dir():
        raise PublishError(f"plot directory {str(out)!r} does not exist")
    paths = [
        _save(manifold_figure(grasps, manifold, base_pose), out / PLOT_FILES[0]),
        _save(hist_figure(grasps), out / PLOT_FILES[1]),
        _save(counts_figure(counts, grasps), out / PLOT_FILES[2]),
    ]
    if "level" in grasps and manifold is not None:
        paths.append(_save(levels_figure(grasps, manifold, base_pose), out / "levels.png"))
    if "patch" in grasps and manifold is not None and (np.asarray(grasps["patch"]) >= 0).any():
        paths.append(_save(patches_figure(grasps, manifold, base_pose), out / "patches.png"))
    if getattr(manifold, "isolation", None) is not None and "dq" in grasps:
        paths.append(plot_coverage(grasps, manifold, out / COVERAGE_FILE))
    return paths
