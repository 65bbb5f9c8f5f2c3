"""Marks and limits of the 2-D chart plots: where the robot is, and axes fitted to the data.

- :func:`robot_side`: where the robot base lies in a manifold's chart (the
  arc length facing it on a cylindrical chart, the direction toward it on a
  spherical one, its position on an ``xy`` / ``pca`` chart), and
  :func:`mark_robot_side` drawing it on the chart's axes;
- :func:`approach_from_base`: the azimuth of an approach from the base, for the
  approach-direction panel of the ``families`` structure;
- :func:`fit_limits`: limits fitted to the data with a small margin, to scale when
  the data's shape allows.

:mod:`gcm_pipeline.outputs.plots` draws the figures.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from gcm_pipeline.geometry.dualquat import dq_translation
from gcm_pipeline.table import GraspTable

__all__ = [
    "BOX",
    "BOX_SHAPE",
    "ROBOT_SIDE_COLOR",
    "RobotSide",
    "approach_from_base",
    "fit_limits",
    "mark_robot_side",
    "robot_side",
]


@dataclass(frozen=True)
class RobotSide:
    """Where the robot base lies as seen in a manifold's 2-D chart (:func:`robot_side`).

    Attributes:
        kind: ``u`` (cylindrical: ``value`` the chart u [m] of the side facing
            the base, drawn as a vertical line), ``ray`` (spherical: ``value``
            the unit direction from the chart origin along which the grasps
            face the base; the stereographic chart keeps the azimuth) or
            ``point`` (``xy`` / ``pca``: ``value`` the base position in the
            chart plane [m]).
        value: ``()`` for ``u``, ``(2,)`` otherwise.
    """

    kind: str
    value: np.ndarray


def robot_side(manifold: Any, base_pose: Any) -> RobotSide | None:
    """The robot base's side in the manifold's chart, or None where it has none.

    The chart frame (``manifold.frame``, (4, 4), the object frame for the
    cylindrical and spherical charts) gives the direction ``d`` from its origin
    to the base's position in chart axes. Cylindrical: ``u = R atan2(d_y, d_x)``
    with ``R = period / (2 pi)`` (in ``[-period / 2, period / 2)`` like the
    chart); spherical: the unit ``(d_x, d_y)``; ``xy`` and ``pca``: ``(d_x, d_y)``.
    None without a base pose or a frame (the ``xy`` chart's frame is the
    world's), for a base on the axis or above the centre, and for other
    projections and the ``families`` structure.

    Args:
        manifold: Object with ``projection``, ``frame`` and ``period``.
        base_pose: The robot base in the world (4, 4) [m], or None.
    """
    projection = getattr(manifold, "projection", None)
    frame = getattr(manifold, "frame", None)
    if base_pose is None or getattr(manifold, "structure", "chart") != "chart":
        return None
    if frame is None and projection == "xy":
        frame = np.eye(4)
    if frame is None or projection not in ("cylindrical", "spherical", "xy", "pca"):
        return None
    frame = np.asarray(frame, dtype=float)
    d = (np.asarray(base_pose, dtype=float)[:3, 3] - frame[:3, 3]) @ frame[:3, :3]
    if projection in ("xy", "pca"):
        return RobotSide("point", d[:2].copy())
    flat = float(np.hypot(d[0], d[1]))
    if flat == 0.0 or flat <= 0.01 * float(np.linalg.norm(d)):  # (nearly) on the axis
        return None
    if projection == "spherical":
        return RobotSide("ray", d[:2] / flat)
    period = getattr(manifold, "period", None)
    if period is None:
        return None
    theta = float(np.arctan2(d[1], d[0]))
    theta = theta - 2 * np.pi if theta >= np.pi else theta
    return RobotSide("u", np.asarray(float(period) * theta / (2 * np.pi)))


ROBOT_SIDE_COLOR = "0.15"


def approach_from_base(grasps: GraspTable, base_pose: Any) -> float | None:
    """Azimuth [deg] of an approach from the robot base toward the grasps' centre.

    The approach direction (grasp frame z) of a grasp on the side of the
    object facing the robot points from the base toward the object: its
    azimuth ``atan2(c_y - b_y, c_x - b_x)`` in (-180, 180], with ``c`` the
    mean grasp position and ``b`` the base position (the approach-direction
    panel of the ``families`` structure's plots marks it). None without a
    base pose or grasps, or with the base (nearly) straight below or above the centre.
    """
    if base_pose is None or "dq" not in grasps or not len(grasps):
        return None
    pos = dq_translation(np.asarray(grasps["dq"], dtype=float))
    d = pos[np.all(np.isfinite(pos), axis=1)].mean(axis=0) - np.asarray(base_pose)[:3, 3]
    if np.hypot(d[0], d[1]) <= 0.01 * np.linalg.norm(d):  # within 0.6 deg of vertical
        return None
    return float(np.degrees(np.arctan2(d[1], d[0])))


def mark_robot_side(ax: Any, side: RobotSide, period: float | None) -> None:
    """Draw ``side`` on chart axes whose limits are set (module :func:`robot_side`)."""
    (x0, x1), (y0, y1) = ax.get_xlim(), ax.get_ylim()
    style = {"color": ROBOT_SIDE_COLOR, "linestyle": "--", "linewidth": 1.2, "zorder": 5}
    text = {"color": ROBOT_SIDE_COLOR, "fontsize": "small", "zorder": 6}
    if side.kind == "u":
        u = float(side.value)
        copies = [u] if not period else u + period * np.arange(-2, 3)
        label = "robot side (facing the base)"
        for x in (c for c in copies if x0 <= c <= x1):
            ax.axvline(x, label=label, **style)
            ax.text(x, 1.01, "robot side", transform=ax.get_xaxis_transform(), ha="center", **text)
            label = None
        return
    centre = np.array([0.5 * (x0 + x1), 0.5 * (y0 + y1)])
    half = np.array([0.5 * (x1 - x0), 0.5 * (y1 - y0)])
    if side.kind == "ray":
        start, direction = np.zeros(2), np.asarray(side.value, dtype=float)
    else:
        point = np.asarray(side.value, dtype=float)
        if np.all(np.abs(point - centre) <= half):  # inside the limits: mark the base itself
            ax.plot(*point, marker="s", color=ROBOT_SIDE_COLOR, ls="", label="robot base", zorder=6)
            return
        start, direction = centre, point - centre
        direction = direction / np.linalg.norm(direction)
    # where the ray leaves the axes (inset a little), from ``start``
    with np.errstate(divide="ignore"):
        reach = (
            np.where(direction > 0, (centre + half - start), (centre - half - start)) / direction
        )
    end = start + 0.96 * float(np.min(np.where(np.isfinite(reach), reach, np.inf))) * direction
    if side.kind == "ray":
        ax.plot(*np.column_stack((start, end)), label="robot side (facing the base)", **style)
        ax.text(*end, "robot side", ha="right" if direction[0] > 0 else "left", **text)
    else:  # an arrow at the edge toward the base; the legend says what it is
        tail = end - 0.15 * np.min(2 * half) * direction
        arrow = {"arrowstyle": "-|>", "color": ROBOT_SIDE_COLOR, "linewidth": 1.5}
        ax.annotate("", xy=end, xytext=tail, arrowprops=arrow, zorder=6)
        away = float(np.linalg.norm(np.asarray(side.value) - centre))
        ax.plot(
            [],
            [],
            marker=">",
            color=ROBOT_SIDE_COLOR,
            label=f"toward the robot base ({away:.2f} m from the middle)",
        )


#: Longer side [in] of a chart's axes box; its shape follows the data within BOX_SHAPE.
BOX = 5.2
BOX_SHAPE = (0.45, 1.6)  # height / width: a strip at most 2.2 times wider, at most 1.6 taller


def fit_limits(ax: Any, xy: np.ndarray, margin: float = 0.04) -> tuple[bool, float, float]:
    """Fit the axes' limits to the points (a small margin); equal aspect when it reads.

    The axes box takes the data's shape (height / width clipped to
    :data:`BOX_SHAPE`). Data at most 3 times longer one way than the other
    are drawn to scale (equal aspect by widening one range, little since the
    box has the data's shape; the box itself keeps its size, and so its
    colour bar's); longer strips fill the box and are not to scale.

    Returns:
        ``(to_scale, width, height)``: the box size [in] the figure is made for.
    """
    xy = xy[np.all(np.isfinite(xy), axis=1)]
    if not len(xy):
        return True, BOX, BOX * 0.8
    lo, hi = xy.min(axis=0), xy.max(axis=0)
    span = hi - lo
    span = np.where(span > 0, span, max(float(span.max()), 1e-3)) * (1.0 + 2.0 * margin)
    centre = 0.5 * (lo + hi)
    ratio = float(span[1] / span[0])
    shape = float(np.clip(ratio, *BOX_SHAPE))
    width, height = (BOX, BOX * shape) if shape <= 1.0 else (BOX / shape, BOX)
    to_scale = 1.0 / 3.0 <= ratio <= 3.0
    if to_scale:  # equal aspect; the shorter range widened to fill the box
        ax.update_datalim(np.vstack((lo, hi)))
        ax.set_xmargin(margin)
        ax.set_ymargin(margin)
        ax.autoscale_view()
        ax.set_aspect("equal", adjustable="datalim")
    else:
        ax.set_xlim(centre[0] - 0.5 * span[0], centre[0] + 0.5 * span[0])
        ax.set_ylim(centre[1] - 0.5 * span[1], centre[1] + 0.5 * span[1])
        ax.set_aspect("auto")
    return to_scale, width, height
