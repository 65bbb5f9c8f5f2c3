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

__all__ = ["MAX_PANELS", "write_coverage_png"]

#: Most panels in one figure.
MAX_PANELS = 12

_POS = ("x", "y")
_FIELDS = {
    "object": ("object_x", "object_y", "object_z", "object_yaw_deg"),
    "base": ("base_x", "base_y", "base_z", "base_yaw_deg"),
}


def _plane(swept: Mapping[str, Sequence[str]]) -> tuple[str, list[str]] | None:
    """The pose whose position axes span the panels, and which of x, y are swept."""
    for pose in ("object", "base"):
        axes = [a for a in _POS if a in swept.get(pose, ())]
        if axes:
            return pose, axes
    return None


def _panel_key(row: Mapping[str, Any], swept: Mapping[str, Sequence[str]], plane: str) -> tuple:
    key: list[Any] = [row["object"]]
    for pose in ("object", "base"):
        for a in swept.get(pose, ()):
            if pose == plane and a in _POS:
                continue
            key.append((pose, a, row.get(f"{pose}_{a}")))
    return tuple(key)


def _panel_title(key: tuple, n_objects: int) -> str:
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
    plane = _plane(swept)
    norm = Normalize(0.0, 1.0)
    cmap = "viridis"
    if plane is None:
        fig = Figure(figsize=(7.0, 3.6), dpi=110, layout="constrained")
        _bar_chart(fig.add_subplot(), rows, swept, title, cmap, norm)
        FigureCanvasAgg(fig).print_png(str(path))
        return path

    pose = plane[0]
    grid_rows = [r for r in rows if int(r.get("round", 0)) == 0]
    panels: dict[tuple, list[Mapping[str, Any]]] = {}
    for r in grid_rows:
        panels.setdefault(_panel_key(r, swept, pose), []).append(r)
    keys = list(panels)
    merged = len(keys) > MAX_PANELS
    if merged:  # one panel per object: the best coverage over the other keys
        panels = {}
        for r in grid_rows:
            panels.setdefault((r["object"],), []).append(r)
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
    refined = [
        r
        for r in rows
        if int(r.get("round", 0)) > 0
        and (merged or _panel_key(r, swept, pose) == key)
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
            s=14,
            edgecolors="white",
            linewidths=0.4,
        )
    if failed:
        ax.scatter(*zip(*failed, strict=True), marker="x", c="0.5", s=20)
    best = [r for r in rows if best_id is not None and int(r["id"]) == best_id]
    if best and (merged or _panel_key(best[0], swept, pose) == key):
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
        (str(key[0]) + ", best over the rest") if merged else _panel_title(key, n_objects),
        fontsize=9,
    )
    return image


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
