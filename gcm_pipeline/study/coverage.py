"""``coverage.png``: the coverage (reachable fraction) of a study's placements as a heat map.

The grid's two position axes (the object's x-y when it is swept there, else
the robot base's) span each panel; there is one panel per value of the other
swept keys (yaw, the other pose, the object), up to :data:`MAX_PANELS`
(beyond that a panel shows the best coverage over the rest). Refined
placements are drawn as dots over the grid in the same colours, failed ones
as grey crosses, the best placement as a star. A study without a position
axis gets a bar per placement instead. Drawn with matplotlib's object API on
the Agg canvas (no pyplot).
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

__all__ = [
    "MAX_PANELS",
    "grid_panels",
    "panel_key",
    "panel_title",
    "plane_of",
    "write_coverage_png",
]

#: Most panels in one figure.
MAX_PANELS = 12

_POS = ("x", "y")
_FIELDS = {
    "object": ("object_x", "object_y", "object_z", "object_yaw_deg"),
    "base": ("base_x", "base_y", "base_z", "base_yaw_deg"),
}


def plane_of(swept: Mapping[str, Sequence[str]]) -> tuple[str, list[str]] | None:
    """The pose whose position axes span the panels, and which of x, y are swept."""
    for pose in ("object", "base"):
        axes = [a for a in _POS if a in swept.get(pose, ())]
        if axes:
            return pose, axes
    return None


def panel_key(row: Mapping[str, Any], swept: Mapping[str, Sequence[str]], plane: str) -> tuple:
    """The panel of a placement: its object and its values of the other swept keys."""
    key: list[Any] = [row["object"]]
    for pose in ("object", "base"):
        for a in swept.get(pose, ()):
            if pose == plane and a in _POS:
                continue
            key.append((pose, a, row.get(f"{pose}_{a}")))
    return tuple(key)


def grid_panels(
    rows: Sequence[Mapping[str, Any]], swept: Mapping[str, Sequence[str]], pose: str
) -> tuple[dict[tuple, list[Mapping[str, Any]]], bool]:
    """The grid's (round 0) placements by panel, and whether panels were merged.

    One panel per value of the swept keys other than ``pose``'s x-y; beyond
    :data:`MAX_PANELS` one panel per object (``merged``: a cell then shows the
    best coverage over the rest).
    """
    grid_rows = [r for r in rows if int(r.get("round", 0)) == 0]
    panels: dict[tuple, list[Mapping[str, Any]]] = {}
    for r in grid_rows:
        panels.setdefault(panel_key(r, swept, pose), []).append(r)
    if len(panels) <= MAX_PANELS:
        return panels, False
    panels = {}
    for r in grid_rows:
        panels.setdefault((r["object"],), []).append(r)
    return panels, True


def panel_title(key: tuple, n_objects: int) -> str:
    """A panel's title (``object yaw 20°``), the object named when there are several."""
    parts = [str(key[0])] if n_objects > 1 else []
    for pose, axis, value in key[1:]:
        unit = "°" if axis.endswith("_deg") else " m"
        name = axis.replace("_deg", "")
        parts.append(f"{pose} {name} {value:g}{unit}" if value is not None else f"{pose} {name} ?")
    return ", ".join(parts) or "coverage"


def write_coverage_png(
    rows: Sequence[Mapping[str, Any]],
    swept: Mapping[str, Sequence[str]],
    path: str | Path,
    *,
    best_id: int | None = None,
    title: str = "",
) -> Path:
    """Draw the coverage of the placements into ``path``.

    Args:
        rows: Placement rows (``placements.csv`` fields: ``id, round, object,
            object_x .. base_yaw_deg, coverage, error``).
        swept: ``{"object": [axes], "base": [axes]}``, the swept keys.
        path: The PNG to write.
        best_id: The best placement's id (marked with a star).
        title: Figure title.

    Returns:
        ``path``.
    """
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.colors import Normalize
    from matplotlib.figure import Figure

    path = Path(path)
    objects = list(dict.fromkeys(str(r["object"]) for r in rows))
    plane = plane_of(swept)
    norm = Normalize(0.0, 1.0)
    cmap = "viridis"
    if plane is None:
        fig = Figure(figsize=(7.0, 3.6), dpi=110, layout="constrained")
        _bar_chart(fig.add_subplot(), rows, swept, title, cmap, norm)
        FigureCanvasAgg(fig).print_png(str(path))
        return path

    panels, merged = grid_panels(rows, swept, plane[0])
    keys = list(panels)
    n = len(keys)
    ncols = min(n, 4)
    nrows = math.ceil(n / ncols)
    fig = Figure(figsize=(3.6 * ncols + 1.2, 3.3 * nrows + 0.6), dpi=110, layout="constrained")
    axs = np.atleast_1d(fig.subplots(nrows, ncols, squeeze=False)).reshape(-1)
    image = None
    for ax, key in zip(axs, keys, strict=False):
        image = _draw_panel(
            ax, key, panels[key], rows, swept, plane, merged, best_id, len(objects), cmap, norm
        )
    for ax in axs[n:]:
        ax.set_visible(False)
    if image is not None:
        fig.colorbar(image, ax=axs[:n].tolist(), label="coverage (reachable fraction)", shrink=0.9)
    if title:
        fig.suptitle(title, fontsize=10)
    FigureCanvasAgg(fig).print_png(str(path))
    return path


def _bar_chart(
    ax: Any,
    rows: Sequence[Mapping[str, Any]],
    swept: Mapping[str, Sequence[str]],
    title: str,
    cmap: str,
    norm: Any,
) -> None:
    """Coverage per placement as bars (no plane of two swept position axes)."""
    from matplotlib import colormaps

    ok = [r for r in rows if not r.get("error")]
    labels = [_label(r, swept) for r in ok]
    cov = [float(r["coverage"]) for r in ok]
    colours = [colormaps[cmap](norm(c)) for c in cov]
    ax.bar(range(len(ok)), cov, color=colours)
    ax.set_xticks(range(len(ok)), labels, rotation=60, ha="right", fontsize=7)
    ax.set_ylabel("coverage (reachable fraction)")
    ax.set_ylim(0, 1)
    ax.set_title(title or "coverage per placement")


def _draw_panel(
    ax: Any,
    key: tuple,
    members: Sequence[Mapping[str, Any]],
    rows: Sequence[Mapping[str, Any]],
    swept: Mapping[str, Sequence[str]],
    plane: tuple[str, Sequence[str]],
    merged: bool,
    best_id: int | None,
    n_objects: int,
    cmap: str,
    norm: Any,
) -> Any:
    """One panel: the grid's coverage, the refined placements, failures and the best one."""
    pose, axes = plane
    fx, fy = f"{pose}_{axes[0]}", f"{pose}_{axes[1]}" if len(axes) > 1 else None
    xs = sorted({float(r[fx]) for r in members})
    ys = sorted({float(r[fy]) for r in members}) if fy else [0.0]
    grid = np.full((len(ys), len(xs)), np.nan)
    failed = []
    for r in members:
        i = ys.index(float(r[fy])) if fy else 0
        j = xs.index(float(r[fx]))
        if r.get("error"):
            failed.append((float(r[fx]), float(r[fy]) if fy else 0.0))
            continue
        grid[i, j] = np.fmax(grid[i, j], float(r["coverage"]))
    image = ax.pcolormesh(_edges(xs), _edges(ys), np.ma.masked_invalid(grid), cmap=cmap, norm=norm)
    if fy:
        ax.set_aspect("equal")
    _mark_base(ax, members, pose, fy is not None)
    _cell_values(ax, xs, ys, grid)
    refined = [
        r
        for r in rows
        if int(r.get("round", 0)) > 0
        and (merged or panel_key(r, swept, pose) == key)
        and str(r["object"]) == str(key[0])
        and not r.get("error")
    ]
    if refined:
        ax.scatter(
            [float(r[fx]) for r in refined],
            [float(r[fy]) if fy else 0.0 for r in refined],
            c=[float(r["coverage"]) for r in refined],
            cmap=cmap,
            norm=norm,
            s=_dot_size(ax, refined, fx, fy),
            edgecolors="0.15",
            linewidths=0.3,
            zorder=4,
        )
    if failed:
        ax.scatter(*zip(*failed, strict=True), marker="x", c="0.5", s=20)
    best = [r for r in rows if best_id is not None and int(r["id"]) == best_id]
    if best and (merged or panel_key(best[0], swept, pose) == key):
        b = best[0]
        if str(b["object"]) == str(key[0]):
            ax.scatter(
                [float(b[fx])],
                [float(b[fy]) if fy else 0.0],
                marker="*",
                s=160,
                c="red",
                edgecolors="white",
                linewidths=0.8,
                zorder=5,
            )
    name = "object" if pose == "object" else "robot base"
    ax.set_xlabel(f"{name} {axes[0]} [m]")
    ax.set_ylabel(f"{name} {axes[1]} [m]" if fy else "")
    ax.set_title(
        (str(key[0]) + ", best over the rest") if merged else panel_title(key, n_objects),
        fontsize=9,
    )
    return image


def _dot_size(ax: Any, rows: Sequence[Mapping[str, Any]], fx: str, fy: str | None) -> float:
    """Marker area [pt^2] of the refined dots: at most 6 pt wide, never overlapping."""
    pts = np.array([(float(r[fx]), float(r[fy]) if fy else 0.0) for r in rows])
    if len(pts) < 2:
        return 36.0
    box = ax.get_window_extent()
    x0, x1 = ax.get_xlim()
    scale = box.width / max(abs(x1 - x0), 1e-12) * 72.0 / ax.get_figure().dpi  # pt per metre
    gaps = np.linalg.norm(pts[:, None] - pts[None], axis=-1) + np.eye(len(pts)) * 1e9
    width = float(np.clip(0.7 * gaps.min() * scale, 2.0, 6.0))
    return width * width


def _cell_values(ax: Any, xs: Sequence[float], ys: Sequence[float], grid: np.ndarray) -> None:
    """Print each cell's coverage in it when the cells are large enough to read it."""
    box = ax.get_window_extent()  # before layout: the subplot's share of the figure
    ex, ey = _edges(xs), _edges(ys)
    x0, x1 = ax.get_xlim()
    y0, y1 = ax.get_ylim()
    cell_w = box.width * min(np.diff(ex)) / max(abs(x1 - x0), 1e-12)
    cell_h = box.height * min(np.diff(ey)) / max(abs(y1 - y0), 1e-12)
    if cell_w < 26 or cell_h < 11:
        return
    size = max(5.0, min(8.0, cell_w / 4.0))
    for i, y in enumerate(ys):
        for j, x in enumerate(xs):
            v = grid[i, j]
            if np.isfinite(v):
                colour = "black" if v > 0.6 else "white"
                ax.text(x, y, f"{v:.2f}", ha="center", va="center", fontsize=size, color=colour)


def _mark_base(ax: Any, members: Sequence[Mapping[str, Any]], pose: str, plane_xy: bool) -> None:
    """Mark the robot base (or, when the base is what moves, the object) in the panel's frame."""
    other = "base" if pose == "object" else "object"
    spots = {
        (float(r.get(f"{other}_x") or 0.0), float(r.get(f"{other}_y") or 0.0)) for r in members
    }
    if len(spots) != 1 or not plane_xy:
        return
    (x, y) = next(iter(spots))
    name = "robot base" if other == "base" else "object"
    marker = "s" if other == "base" else "o"
    ax.scatter([x], [y], marker=marker, s=70, c="#d62728", edgecolors="white", zorder=6)
    ax.annotate(
        name, (x, y), xytext=(6, 6), textcoords="offset points", fontsize=7, color="#d62728"
    )
    ax.update_datalim([(x, y)])
    ax.autoscale_view()


def _edges(values: Sequence[float]) -> np.ndarray:
    """Cell edges around sorted centres (midpoints; half a step past the ends)."""
    v = np.asarray(values, dtype=float)
    if v.size == 1:
        return np.array([v[0] - 0.05, v[0] + 0.05])
    mid = 0.5 * (v[1:] + v[:-1])
    return np.concatenate([[v[0] - (mid[0] - v[0])], mid, [v[-1] + (v[-1] - mid[-1])]])


def _label(row: Mapping[str, Any], swept: Mapping[str, Sequence[str]]) -> str:
    parts = [str(row["object"])]
    for pose in ("object", "base"):
        for a in swept.get(pose, ()):
            parts.append(f"{a} {float(row[f'{pose}_{a}']):g}")
    return " ".join(parts)
