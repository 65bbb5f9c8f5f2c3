"""PNG plots of a run: the manifold chart, coverage, the manipulability histogram, counts.

Figures are drawn with matplotlib's object API on the Agg canvas (no pyplot,
no global backend switch), so plotting works headless and from threads.
"""

from __future__ import annotations

import os
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from gcm_pipeline.errors import PublishError
from gcm_pipeline.geometry.dualquat import dq_translation
from gcm_pipeline.outputs.pose_view import PoseView, equal_axes
from gcm_pipeline.table import GraspTable

__all__ = [
    "COVERAGE_FILE",
    "PLOT_FILES",
    "REASON_COLORS",
    "candidate_rows",
    "chart_axis_labels",
    "chart_period",
    "candidate_coverage",
    "chart_points",
    "colormap",
    "plot_coverage",
    "reason_palette",
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
    try:
        fig.savefig(path, dpi=_DPI)
    except OSError as exc:
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


def _chart_figure(grasps: GraspTable, manifold: Any) -> tuple[Any, Any, np.ndarray, str]:
    """A figure with the manifold's triangles drawn in its chart.

    Returns:
        ``(fig, ax, pts, projection)``: ``pts`` (N, 2) the chart coordinates of
        every row (NaN where a row cannot be placed).
    """
    fig = _figure((7.0, 6.0))
    ax = fig.add_subplot()
    projection = str(getattr(manifold, "projection", "") or "")
    chart = np.asarray(getattr(manifold, "chart", np.empty((0, 2))), dtype=float)
    tris = np.asarray(getattr(manifold, "triangles", np.empty((0, 3))), dtype=np.int64)
    period = chart_period(grasps, manifold) if len(chart) else None
    if len(chart) and len(tris):
        from matplotlib.collections import PolyCollection

        corners = _unwrap(chart[tris], period)
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
        ax.update_datalim(corners.reshape(-1, 2))
        ax.autoscale_view()
    pts = (
        chart_points(grasps, manifold, period) if len(chart) else np.full((len(grasps), 2), np.nan)
    )
    return fig, ax, pts, projection


def _finish_chart(ax: Any, projection: str, title: str) -> None:
    u_label, v_label = chart_axis_labels(projection)
    ax.set_xlabel(u_label)
    ax.set_ylabel(v_label)
    ax.set_title(f"{title} ({projection} projection)" if projection else title)
    ax.set_aspect("equal", adjustable="datalim")
    if ax.get_legend_handles_labels()[0]:
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


class _ChartView:
    """The one 2-D chart of the ``chart`` structure, with the interface of :class:`PoseView`."""

    def __init__(self, grasps: GraspTable, manifold: Any) -> None:
        self.fig, self.ax, self.pts, self.projection = _chart_figure(grasps, manifold)
        self.placed = np.all(np.isfinite(self.pts), axis=1)
        self.colorbar_axes = self.legend_axes = self.ax

    def scatter(self, sel: np.ndarray, *, label: str | None = None, **kw: Any) -> Any:
        sel = sel & self.placed
        return self.ax.scatter(self.pts[sel, 0], self.pts[sel, 1], label=label, **kw)

    def finish(self, title: str) -> None:
        _finish_chart(self.ax, self.projection, title)


def _view(grasps: GraspTable, manifold: Any, what: str) -> tuple[Any, str]:
    """The view to draw on and the title's suffix for the manifold's structure.

    The ``families`` structure is drawn in the world (:class:`PoseView`), the
    ``chart`` structure in its chart.
    """
    if getattr(manifold, "structure", "chart") != "families" or "dq" not in grasps:
        return _ChartView(grasps, manifold), what
    view = PoseView(
        _figure((12.0, 5.8)), grasps, manifold, candidate_rows(grasps, len(manifold.chart))
    )
    family = getattr(manifold, "family", None)
    if family is None:  # a manifold.npz without it: no count to give
        return view, f"{what}, {len(manifold.triangles)} triangles"
    fams = int(np.max(family, initial=-1)) + 1
    return view, f"{what}, {len(manifold.triangles)} triangles in {fams} families"


def _plot_levels(grasps: GraspTable, manifold: Any, path: Path) -> Path:
    """Adaptive refinement: rows coloured by level, unreachable as crosses."""
    view, suffix = _view(grasps, manifold, "")
    level = np.asarray(grasps["level"], dtype=np.int64)
    reach = np.asarray(grasps.get("reachable", np.ones(len(grasps), bool)), dtype=bool)
    size = float(np.clip(3000.0 / max(len(grasps), 1), 2.0, 30.0))
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
    return _save(view.fig, path)


def _plot_patches(grasps: GraspTable, manifold: Any, path: Path) -> Path:
    """IK continuity: reachable rows coloured by patch (one IK branch each)."""
    view, suffix = _view(grasps, manifold, "")
    patch = np.asarray(grasps["patch"], dtype=np.int64)
    size = float(np.clip(3000.0 / max(len(grasps), 1), 2.0, 30.0))
    tab = colormap("tab10")
    ids, counts = np.unique(patch[patch >= 0], return_counts=True)
    for k, (pid, n) in enumerate(zip(ids.tolist(), counts.tolist(), strict=True)):
        view.scatter(
            patch == pid,
            s=size,
            color=tab(pid % 10),
            edgecolors="none",
            label=f"patch {pid} ({n})" if k < _PATCH_LABELS else None,
            zorder=3,
            rasterized=len(grasps) > 5000,
        )
    if len(ids) > _PATCH_LABELS:  # the rest share the ten colours: say so in the legend
        rest = int(counts[_PATCH_LABELS:].sum())
        more = len(ids) - _PATCH_LABELS
        view.legend_axes.plot(
            [], [], "o", color="0.4", markersize=4, label=f"{more} smaller patches ({rest} grasps)"
        )
    bad = patch < 0
    if bad.any():
        view.scatter(
            bad,
            s=size,
            marker="x",
            color="0.7",
            linewidths=0.6,
            label=f"unreachable ({int(bad.sum())})",
            zorder=2,
            rasterized=len(grasps) > 5000,
        )
    view.finish(f"IK branches: {len(ids)} patches" + suffix)
    return _save(view.fig, path)


def _plot_manifold(grasps: GraspTable, manifold: Any, path: Path) -> Path:
    """Reachable rows coloured by manipulability, unreachable ones by reason, candidates ringed."""
    view, suffix = _view(grasps, manifold, "")
    chart = np.asarray(getattr(manifold, "chart", np.empty((0, 2))), dtype=float)
    reach = np.asarray(grasps.get("reachable", np.zeros(len(grasps), bool)), dtype=bool)
    manip = np.asarray(grasps.get("manipulability", np.full(len(grasps), np.nan)), dtype=float)
    size = float(np.clip(3000.0 / max(len(grasps), 1), 1.0, 30.0))
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
        view.fig.colorbar(sc, ax=view.colorbar_axes, label="manipulability [-]")
    cand = np.asarray(grasps.get("origin", np.array([], dtype=str))).astype(str) == "candidate"
    # rings stay readable up to a few hundred candidates; beyond, coverage.png shows them
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
    return _save(view.fig, path)


def _placed(view: Any, sel: np.ndarray) -> np.ndarray:
    """``sel`` restricted to the rows the view can place (all rows in the world view)."""
    placed = getattr(view, "placed", None)
    return sel if placed is None else sel & placed


def _plot_hist(grasps: GraspTable, path: Path) -> Path:
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
    ax.set_xlabel("manipulability [-]")
    ax.set_ylabel("reachable grasps [count]")
    ax.set_title(f"Manipulability of the reachable grasps (n = {values.size})")
    ax.grid(alpha=0.25, axis="y")
    return _save(fig, path)


def _plot_counts(counts: Mapping[str, int], path: Path) -> Path:
    fig = _figure()
    ax = fig.add_subplot()
    keys = [k for k in _COUNT_ORDER if k in counts] + [k for k in counts if k not in _COUNT_ORDER]
    values = [int(counts[k]) for k in keys]
    colors = ["#4a90d9", "#7f7f7f", "#c7c7c7", "#5aa469", "#21918c"]
    bars = ax.bar(
        range(len(keys)), values, color=[colors[i % len(colors)] for i in range(len(keys))]
    )
    ax.bar_label(bars, labels=[f"{v:,}" for v in values], padding=2, fontsize="small")
    ax.set_xticks(range(len(keys)), [k.replace("_", "\n") for k in keys])
    ax.set_ylabel("count [-]")
    ax.set_title("Per-stage counts")
    if values and max(values) > 0 and max(values) > 50 * max(1, min(v for v in values if v > 0)):
        ax.set_yscale("log")
        ax.set_ylabel("count [-] (log scale)")
    ax.margins(y=0.12)
    ax.grid(alpha=0.25, axis="y")
    return _save(fig, path)


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
        _plot_manifold(grasps, manifold, out / PLOT_FILES[0]),
        _plot_hist(grasps, out / PLOT_FILES[1]),
        _plot_counts(counts, out / PLOT_FILES[2]),
    ]
    if "level" in grasps and manifold is not None:
        paths.append(_plot_levels(grasps, manifold, out / "levels.png"))
    if "patch" in grasps and manifold is not None and (np.asarray(grasps["patch"]) >= 0).any():
        paths.append(_plot_patches(grasps, manifold, out / "patches.png"))
    if getattr(manifold, "isolation", None) is not None and "dq" in grasps:
        paths.append(plot_coverage(grasps, manifold, out / COVERAGE_FILE))
    return paths
