"""Manifold stage: triangles linking the grasp candidates.

Two structures (``structure``): ``families`` links grasps that are near in
the pose metric, each family of grasps in its own chart
(:mod:`gcm_pipeline.manifold.families`); ``chart`` is the paper's.

The paper (section III) projects the grasp positions onto the XY plane, drops
the orientation and triangulates the 2-D points. The triangles are
the cells inside which :mod:`gcm_pipeline.manifold.densify` blends poses.
The 2-D charts (``projection``: ``xy``, ``pca``, ``cylindrical``,
``spherical``) and their triangulation are in :mod:`gcm_pipeline.manifold.charts`.

Pruning
-------
A triangle is dropped when its longest edge, measured between the 3-D
positions, exceeds ``max_edge_length`` [m] (reason ``edge_length``), or else
when two of its vertex orientations differ by more than
``max_edge_angle_deg`` [deg] (reason ``edge_angle``). So the mesh never links
grasps on opposite sides of an object or with very different orientations.
Candidates used by no kept triangle stay grasps of the table
(:attr:`Manifold.unused`).
"""

from __future__ import annotations

from collections import Counter
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from gcm_pipeline.errors import GeometryError, InputError, choice_error
from gcm_pipeline.geometry.bowyer_watson import TRIANGULATORS
from gcm_pipeline.geometry.dualquat import dq_angle_distance, dq_to_matrix
from gcm_pipeline.geometry.pose_metric import ORIENTATION_SCALE
from gcm_pipeline.manifold.charts import PROJECTIONS, chart_triangles
from gcm_pipeline.manifold.families import family_triangles
from gcm_pipeline.manifold.repeats import same_pose_rows
from gcm_pipeline.table import GraspTable

__all__ = ["STRUCTURES", "Manifold", "build_manifold", "candidate_poses"]

#: Manifold structures: pose-metric families or the paper's one 2-D chart.
STRUCTURES = ("chart", "families")

_EMPTY_TRIS = np.zeros((0, 3), dtype=np.int64)


@dataclass(frozen=True, eq=False, repr=False)
class Manifold:
    """A triangle mesh over the grasp candidates (arrays read-only).

    Attributes:
        chart: (N, 2) chart coordinates [m] of the N candidates, in table order
            (stereographic ones scaled by ``2 R`` for ``spherical``).
        triangles: (T, 3) int candidate row ids of the kept triangles
            (counter-clockwise in the chart, unwrapped for ``cylindrical``).
        dropped: (D, 3) int candidate row ids of the pruned triangles.
        dropped_reason: (D,) str, ``edge_length`` or ``edge_angle``.
        projection: The chart's name (see :data:`~gcm_pipeline.manifold.charts.PROJECTIONS`).
        triangulator: ``qhull`` or ``bowyer_watson``.
        frame: (4, 4) pose of the chart frame in the world (the object frame or
            the estimated one; identity for ``xy``).
        period: Period [m] of the chart's first coordinate (one turn,
            ``2 pi R`` for ``cylindrical``, ``R`` the chart's reference
            radius), else ``None``.
        structure: ``chart`` or ``families`` (then ``projection`` is
            ``families`` and ``chart`` the families' atlas).
        family: (N,) family of each candidate (``families``; -1 for a
            duplicate pose), else None.
        isolation: (N,) why a candidate is in no triangle (``families``:
            ``""``, ``duplicate``, ``no_neighbour``, ``no_triple``), else None.
        max_edge_length: The position bound every triangle keeps [m]
            (``families``: the given or derived one), else None.
        max_edge_angle_deg: The orientation bound [deg] (``families``), else None.
    """

    chart: np.ndarray
    triangles: np.ndarray
    dropped: np.ndarray
    dropped_reason: np.ndarray
    projection: str
    triangulator: str = "qhull"
    frame: np.ndarray | None = None
    period: float | None = None
    structure: str = "chart"
    family: np.ndarray | None = None
    isolation: np.ndarray | None = None
    max_edge_length: float | None = None
    max_edge_angle_deg: float | None = None

    def __post_init__(self) -> None:
        for name in (
            "chart",
            "triangles",
            "dropped",
            "dropped_reason",
            "frame",
            "family",
            "isolation",
        ):
            arr = getattr(self, name)
            if isinstance(arr, np.ndarray):
                arr.setflags(write=False)

    @property
    def n_vertices(self) -> int:
        """Number N of candidates (rows of :attr:`chart`)."""
        return len(self.chart)

    @property
    def vertex_ids(self) -> np.ndarray:
        """(N,) candidate row ids of the chart rows: ``arange(N)``."""
        return np.arange(len(self.chart))

    @property
    def unused(self) -> np.ndarray:
        """(U,) candidate row ids that no kept triangle uses (still grasps to check)."""
        used = np.zeros(len(self.chart), dtype=bool)
        used[self.triangles.ravel()] = True
        return np.flatnonzero(~used)

    @property
    def isolated_counts(self) -> dict[str, int]:
        """Candidates in no kept triangle, per reason (``unused`` for the chart structure)."""
        if self.isolation is None:
            return {"unused": len(self.unused)} if len(self.unused) else {}
        reasons = self.isolation[self.isolation != ""]
        return dict(sorted(Counter(reasons.tolist()).items()))

    @property
    def dropped_counts(self) -> dict[str, int]:
        """Number of dropped triangles per reason."""
        return dict(sorted(Counter(self.dropped_reason.tolist()).items()))

    def blend_chart(self, vertices: npt.ArrayLike, weights: npt.ArrayLike) -> np.ndarray:
        """Chart coordinates of barycentric blends, unwrapped across a periodic seam.

        Args:
            vertices: (M, 3) candidate row ids (e.g. the densified table's
                ``vertices`` column).
            weights: (M, 3) barycentric weights.

        Returns:
            (M, 2) chart coordinates; for a periodic chart the first coordinate
            is blended on the unwrapped triangle and wrapped back into
            ``[-period / 2, period / 2)``.
        """
        corners = self.chart[np.asarray(vertices, dtype=np.int64)]
        w = np.asarray(weights, dtype=np.float64)
        if self.period is None:
            return np.einsum("mk,mkd->md", w, corners)
        corners = corners.copy()
        x = corners[..., 0]
        x -= self.period * np.round((x - x[:, :1]) / self.period)
        out = np.einsum("mk,mkd->md", w, corners)
        out[:, 0] = (out[:, 0] + 0.5 * self.period) % self.period - 0.5 * self.period
        return out

    def __repr__(self) -> str:
        reasons = ", ".join(f"{k}: {v}" for k, v in self.dropped_counts.items())
        dropped = f"{len(self.dropped)} dropped" + (f" ({reasons})" if reasons else "")
        head = "" if self.structure == "chart" else f"structure={self.structure!r}, "
        return (
            f"Manifold({head}projection={self.projection!r}, triangulator={self.triangulator!r}, "
            f"{self.n_vertices} vertices, {len(self.triangles)} triangles, {dropped}, "
            f"{len(self.unused)} unused)"
        )


# --------------------------------------------------------------------------- inputs
def candidate_poses(grasps: GraspTable) -> np.ndarray:
    """The ``dq`` column (N, 8) of a candidate table, validated.

    Raises:
        InputError: If the table has no ``dq`` column.
        GeometryError: On a wrong shape, non-finite values, a zero-norm
            rotation or fewer than 3 poses.
    """
    if "dq" not in grasps:
        raise InputError(f"grasp table has no column 'dq'; columns: {', '.join(grasps.columns)}")
    dq = np.asarray(grasps["dq"], dtype=np.float64)
    if dq.ndim != 2 or dq.shape[1] != 8:
        raise GeometryError(f"grasp column 'dq' must have shape (N, 8), got {dq.shape}")
    finite = np.isfinite(dq).all(axis=1)
    if not finite.all():
        raise GeometryError(f"grasp column 'dq' has non-finite values at row {np.argmin(finite)}")
    norm = np.linalg.norm(dq[:, :4], axis=1)
    if (norm < 1e-12).any():
        raise GeometryError(
            f"grasp column 'dq' has a zero-norm rotation at row {int(np.argmax(norm < 1e-12))}"
        )
    if len(dq) < 3:
        raise GeometryError(f"need at least 3 grasp poses to build a manifold, got {len(dq)}")
    return dq


def _families(
    dq: np.ndarray,
    triangulator: str,
    max_edge_length: float | None,
    max_edge_angle_deg: float | None,
    orientation_scale: float,
) -> Manifold:
    """The manifold of the ``families`` structure (:mod:`gcm_pipeline.manifold.families`)."""
    fm = family_triangles(
        dq,
        max_edge_length=max_edge_length,
        max_edge_angle_deg=max_edge_angle_deg,
        orientation_scale=orientation_scale,
        triangulator=triangulator,
    )
    return Manifold(
        chart=fm.chart,
        triangles=fm.triangles,
        dropped=fm.dropped,
        dropped_reason=fm.dropped_reason,
        projection="families",
        triangulator=triangulator,
        structure="families",
        family=fm.family,
        isolation=fm.isolation,
        max_edge_length=fm.max_edge_length,
        max_edge_angle_deg=fm.max_edge_angle_deg,
    )


# --------------------------------------------------------------------------- stage
def build_manifold(
    grasps: GraspTable,
    *,
    structure: str = "chart",
    projection: str = "xy",
    triangulator: str = "qhull",
    max_edge_length: float | None = None,
    max_edge_angle_deg: float | None = None,
    frame: npt.ArrayLike | None = None,
    orientation_scale: float = ORIENTATION_SCALE,
) -> Manifold:
    """Triangulate the candidates and prune long or twisted triangles.

    Args:
        grasps: Candidate table with column ``dq`` (N, 8), world-frame grasp poses.
        structure: ``chart`` (the paper's: one 2-D chart of all candidates,
            ``projection``) or ``families`` (grasps near in the pose metric,
            one chart per family; ``projection`` and ``frame`` unused,
            unset bounds derived from the data's spacing; see
            :mod:`gcm_pipeline.manifold.families`).
        projection: Chart: ``xy`` (the paper's), ``pca``, ``cylindrical`` or
            ``spherical`` (see :mod:`gcm_pipeline.manifold.charts`).
        triangulator: ``qhull`` (default) or ``bowyer_watson`` (the paper's).
        max_edge_length: Drop triangles whose longest edge between the 3-D
            positions exceeds this [m]; ``None`` keeps all.
        max_edge_angle_deg: Drop triangles two of whose vertex orientations
            differ by more than this [deg]; ``None`` keeps all.
        frame: (4, 4) pose of the object frame in the world, used by the
            cylindrical and spherical charts (z axis, origin).
        orientation_scale: ``L`` [m/rad] of the pose metric (``families``).

    Returns:
        The :class:`Manifold`.

    Raises:
        GeometryError: On an unknown projection or triangulator, invalid
            poses, fewer than 3 poses, a non-rigid frame, non-positive
            thresholds, or candidates all duplicate or collinear in the chart.
        InputError: If ``grasps`` has no ``dq`` column.
    """
    if structure not in STRUCTURES:
        raise choice_error(GeometryError, "structure", structure, STRUCTURES)
    if projection not in PROJECTIONS:
        raise choice_error(GeometryError, "projection", projection, PROJECTIONS)
    if triangulator not in TRIANGULATORS:
        raise choice_error(GeometryError, "triangulator", triangulator, TRIANGULATORS)
    for name, value, upper in (
        ("max_edge_length", max_edge_length, np.inf),
        ("max_edge_angle_deg", max_edge_angle_deg, 180.0),
    ):
        if value is not None and not (0 < float(value) <= upper):
            raise GeometryError(f"{name} must be in (0, {upper:g}], got {value!r}")
    dq = candidate_poses(grasps)
    if structure == "families":
        return _families(dq, triangulator, max_edge_length, max_edge_angle_deg, orientation_scale)
    pose = dq_to_matrix(dq)
    pos, approach = pose[:, :3, 3], pose[:, :3, 2]
    frame_arr = None if frame is None else np.asarray(frame, dtype=np.float64)

    chart, tris, used_frame, period = chart_triangles(
        pos, approach, projection, triangulator, frame_arr, same_pose_rows(dq, orientation_scale)
    )

    reason = np.full(len(tris), "", dtype="<U11")
    if len(tris):
        if max_edge_length is not None:
            p = pos[tris]
            longest = np.linalg.norm(p - np.roll(p, -1, axis=1), axis=2).max(axis=1)
            reason[longest > max_edge_length] = "edge_length"
        if max_edge_angle_deg is not None:
            q = dq[tris]
            angle = dq_angle_distance(q, np.roll(q, -1, axis=1)).max(axis=1)
            reason[(reason == "") & (angle > np.deg2rad(max_edge_angle_deg))] = "edge_angle"
    kept = reason == ""
    tris = tris.astype(np.int64)
    return Manifold(
        chart=chart,
        triangles=tris[kept] if len(tris) else _EMPTY_TRIS.copy(),
        dropped=tris[~kept] if len(tris) else _EMPTY_TRIS.copy(),
        dropped_reason=reason[~kept],
        projection=projection,
        triangulator=triangulator,
        frame=used_frame,
        period=period,
    )
