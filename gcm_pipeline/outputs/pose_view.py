"""The manifold drawn in the world: grasp positions in 3-D beside their approach directions.

The ``families`` structure has no single 2-D chart worth looking at (each
family's own chart is a local linear embedding of position and orientation
together; laid side by side they read as one blob). Its plots show what a
roboticist checks instead:

- **left**, the grasp positions in the world [m] with the triangles drawn
  between candidates (equal scale on the three axes);
- **right**, the approach direction of every grasp (the grasp frame's z axis
  in the world) as azimuth and elevation [deg]: grasps at one position from
  several sides separate here, and ``-90`` is a grasp from straight above.

Both panels show every row with the same colours, so a point can be found in
each. matplotlib is imported by :mod:`gcm_pipeline.outputs.plots`, which
makes the figure.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from gcm_pipeline.geometry.dualquat import dq_to_matrix, dq_translation
from gcm_pipeline.table import GraspTable

__all__ = ["PoseView", "approach_angles", "equal_axes"]

#: Horizontal length of a unit axis below which it is vertical (rounding noise of a rotation).
_VERTICAL = 1e-9


def approach_angles(dq: np.ndarray) -> np.ndarray:
    """(N, 2) azimuth and elevation [deg] of each grasp frame's z axis in the world.

    Azimuth ``atan2(z_y, z_x)`` in (-180, 180], elevation ``asin(z_z)`` in
    [-90, 90] (``-90``: the gripper approaches straight down). A vertical
    axis has no azimuth: 0 (not the rounding noise of its x and y, which
    would scatter grasps from straight above along the whole azimuth axis).
    """
    rot = dq_to_matrix(np.asarray(dq, dtype=np.float64).reshape(-1, 8))[:, :3, :3]
    z = rot[:, :, 2]
    vertical = np.hypot(z[:, 0], z[:, 1]) < _VERTICAL
    az = np.where(vertical, 0.0, np.degrees(np.arctan2(z[:, 1], z[:, 0])))
    el = np.degrees(np.arcsin(np.clip(z[:, 2], -1.0, 1.0)))
    return np.column_stack((az, el))


class PoseView:
    """Two panels of one figure (module docstring); ``scatter`` draws on both.

    Args:
        fig: A matplotlib figure with no axes yet.
        grasps: The grasp table (``dq`` used).
        manifold: Object with ``triangles`` (T, 3) candidate ids; the
            candidates are the table's first rows of ``origin`` ``candidate``
            (``rows`` gives their table rows).
        rows: (N,) table rows of the candidates, in candidate order.
    """

    def __init__(self, fig: Any, grasps: GraspTable, manifold: Any, rows: np.ndarray) -> None:
        self.fig = fig
        dq = np.asarray(grasps["dq"], dtype=np.float64)
        self.pos = dq_translation(dq)
        self.angles = approach_angles(dq)
        self.space = fig.add_subplot(1, 2, 1, projection="3d")
        self.directions = fig.add_subplot(1, 2, 2)
        self.colorbar_axes = self.directions
        self.legend_axes = self.space  # the axes whose handles make the figure's legend
        tris = np.asarray(getattr(manifold, "triangles", np.empty((0, 3))), dtype=np.int64)
        tris = tris.reshape(-1, 3)
        if len(tris) and len(rows):
            from mpl_toolkits.mplot3d.art3d import Line3DCollection

            corners = self.pos[np.asarray(rows)[tris]]
            seg = corners[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2, 3)
            self.space.add_collection3d(
                Line3DCollection(seg, colors="0.6", linewidths=0.25, alpha=0.3)
            )
            # a proxy for the legend (a 3-D line collection has no legend handle)
            self.space.plot([], [], color="0.6", linewidth=0.8, label=f"triangles ({len(tris)})")

    def scatter(self, sel: np.ndarray, *, label: str | None = None, **kw: Any) -> Any:
        """Scatter rows ``sel`` on both panels (the label once); returns the 2-D artist."""
        if not np.any(sel):
            return None
        kw.pop("zorder", None)  # 3-D axes order by depth
        self.space.scatter(*self.pos[sel].T, label=label, **kw)
        return self.directions.scatter(*self.angles[sel].T, **kw)

    def finish(self, title: str) -> None:
        """Axis labels, equal 3-D scale, the legend below both panels and the titles."""
        self.space.set_xlabel("x [m]")
        self.space.set_ylabel("y [m]")
        self.space.set_zlabel("z [m]")
        equal_axes(self.space, self.pos)
        self.space.set_title("Positions in the world", fontsize="medium")
        ax = self.directions
        ax.set_xlim(-180, 180)
        ax.set_ylim(-92, 92)
        ax.set_xticks(np.arange(-180, 181, 60))
        ax.set_yticks(np.arange(-90, 91, 30))
        ax.set_xlabel("approach azimuth [deg] (grasp z axis)")
        ax.set_ylabel("approach elevation [deg] (-90 = from above)")
        ax.set_title("Approach directions", fontsize="medium")
        ax.grid(alpha=0.25)
        self.fig.suptitle(title)
        handles, labels = self.space.get_legend_handles_labels()
        if handles:
            legend = self.fig.legend(
                handles, labels, loc="outside lower center", ncols=3, fontsize="small"
            )
            for handle in legend.legend_handles:
                if hasattr(handle, "set_sizes"):
                    handle.set_sizes([24.0])


def equal_axes(ax: Any, pos: np.ndarray) -> None:
    """Equal scale on the three axes around the points."""
    pos = pos[np.all(np.isfinite(pos), axis=1)]
    if not len(pos):
        return
    centre = 0.5 * (pos.min(axis=0) + pos.max(axis=0))
    half = max(0.5 * float(np.ptp(pos, axis=0).max()), 1e-3)
    ax.set_xlim(centre[0] - half, centre[0] + half)
    ax.set_ylim(centre[1] - half, centre[1] + half)
    ax.set_zlim(centre[2] - half, centre[2] + half)
