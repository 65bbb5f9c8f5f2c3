"""The 2-D charts of the grasp candidates, and their triangulation.

:func:`chart_triangles` maps the grasp positions (and approach axes) onto a
plane and triangulates them there; :mod:`gcm_pipeline.manifold.build` prunes
the triangles and keeps them as the :class:`~gcm_pipeline.manifold.build.Manifold`.

Charts (``projection``)
-----------------------

=============== ===============================================================
``xy``          the paper's: world (x, y) of the grasp positions [m]. Grasps
                with the same x, y and different z collapse onto one point
                (the paper's known problem); only the first is a vertex.
``pca``         coordinates [m] in the best-fit plane of the positions (the two
                principal axes), for flat grasp sets in any orientation.
``cylindrical`` ``(R * theta, h)`` [m]: arc length at one reference radius
                ``R`` and height along the axis, for grasps around an
                elongated object (see *Angles* below). The chart is periodic
                in ``theta`` with period ``2 pi R``: it is triangulated with
                copies shifted by one turn and every triangle is kept once, so
                the mesh closes around the object with no seam at +-pi.
                ``theta`` of the stored chart is in [-pi, pi); a triangle over
                the seam is counter-clockwise in the unwrapped chart.
``spherical``   stereographic projection (scaled by ``2 R``, dimensionless
                directions times [m]) from the pole below the object. It maps
                circles to circles, so the planar Delaunay triangulation is the
                spherical one; triangles whose circumcircle contains the pole
                are left out (grasp sets rarely surround the pole).
=============== ===============================================================

Repeats of a pose (exact, or within 1e-5 m in the pose metric:
:mod:`gcm_pipeline.manifold.repeats`) are one point: the chart is made and
triangulated over the first row of each pose, each pose once (so the
chart's frame and radius do not follow how often a pose is repeated), and
every repeat takes its first row's chart point; repeats are in no triangle.

The cylindrical and spherical charts use the object frame ``frame`` (its z
axis is the cylinder axis / the direction away from the pole, its origin the
centre, its x axis the ``theta = 0`` direction). Without it they use the
grasps' centroid and the principal axis (of the positions) about which the
standoff points (see *Angles*) lie closest to a cylinder (the largest-variance
axis of a tall grasp set, the normal of a flat ring; judged on the standoff
points because deep side grasps put the tool points on the axis itself), and
for the sphere the least-squares sphere centre and the grasps'
mean direction from it (the pole is opposite).

Angles
------
The angle of grasp ``i`` about the axis (cylindrical) or its direction from
the centre (spherical) is that of ``v_i = (p_i - o) - L a_i`` (for the
cylinder only its component perpendicular to the axis), with ``p_i`` the grasp
position, ``o`` the chart origin, ``a_i`` the approach axis (grasp frame z,
into the object) and ``L`` = :data:`STANDOFF`: the point one standoff back
along the approach. A grasp whose tool point sits on or near the axis (a
centred side grasp deep in a thin bottle, as parallel grippers and ACRONYM
imports give) still gets the angle it is approached from instead of the noise
of its position; for radial grasps it is the position's angle and for grasps
approached along the axis (top grasps) it is the position's angle too. The
reference radius ``R`` is the median ``|v_i|`` (the same for every grasp), so
the chart's scale does not shrink as the tool points move toward the axis.
"""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

from gcm_pipeline.errors import GeometryError
from gcm_pipeline.geometry.bowyer_watson import check_triangulable, delaunay
from gcm_pipeline.geometry.dualquat import dq_from_matrix

__all__ = ["PROJECTIONS", "STANDOFF", "chart_triangles"]

PROJECTIONS = ("cylindrical", "pca", "spherical", "xy")

#: Standoff [m] along the approach that gives a grasp its angle in the
#: cylindrical and spherical charts: the angle is taken of the point one
#: standoff back along the approach, so a grasp whose tool point sits on or
#: near the axis (centre) still gets the angle it is approached from; for
#: grasps approached along the axis (top grasps) it is the position's angle.
STANDOFF = 0.10

_JITTER = 1e-9  # relative tie-breaking offset of the periodic chart


def _frame_axes(frame: npt.ArrayLike) -> tuple[np.ndarray, np.ndarray]:
    """Validate a (4, 4) rigid frame; return (origin (3,), rotation (3, 3))."""
    m = np.asarray(frame, dtype=np.float64)
    if m.shape != (4, 4):
        raise GeometryError(f"frame must be a (4, 4) pose, got shape {m.shape}")
    try:
        dq_from_matrix(m)
    except GeometryError as exc:
        raise GeometryError(f"frame: {exc}") from None
    return m[:3, 3].copy(), m[:3, :3].copy()


def _basis_from_axis(axis: np.ndarray) -> np.ndarray:
    """Right-handed rotation (3, 3) whose z column is ``axis`` (deterministic x)."""
    z = axis / np.linalg.norm(axis)
    helper = np.eye(3)[int(np.argmin(np.abs(z)))]
    x = np.cross(helper, z)
    x /= np.linalg.norm(x)
    return np.column_stack((x, np.cross(z, x), z))


def _principal_axes(pos: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Centroid (3,) and principal axes (3, 3) (columns, decreasing variance, right-handed)."""
    centre = pos.mean(axis=0)
    _, _, vt = np.linalg.svd(pos - centre, full_matrices=False)
    axes = vt.T.copy()
    for k in range(3):  # deterministic signs: largest component positive
        if axes[np.argmax(np.abs(axes[:, k])), k] < 0:
            axes[:, k] *= -1
    if np.linalg.det(axes) < 0:
        axes[:, 2] *= -1
    return centre, axes


def _cylinder_axis(rel: np.ndarray, axes: np.ndarray) -> int:
    """Index of the principal axis about which the points lie closest to a cylinder.

    The relative spread (std / mean) of the distances from each principal
    axis through the centroid is smallest for the cylinder's axis, whether the
    grasp set is tall (axis = largest variance) or a flat ring (axis = normal).
    """
    scores = []
    for k in range(3):
        along = rel @ axes[:, k]
        rho = np.linalg.norm(rel - along[:, None] * axes[:, k], axis=1)
        mean = float(rho.mean())
        scores.append(float(rho.std()) / mean if mean > 0 else np.inf)
    return int(np.argmin(scores))


def _sphere_centre(pos: np.ndarray) -> np.ndarray:
    """Least-squares sphere centre of the points (the centroid if they are coplanar).

    Solves ``|p|^2 = 2 c . p + k`` linearly; exact for points on a sphere.
    """
    centroid = pos.mean(axis=0)
    rel = pos - centroid
    a = np.column_stack((2.0 * rel, np.ones(len(rel))))
    sol, _, rank, sv = np.linalg.lstsq(a, (rel * rel).sum(axis=1), rcond=None)
    if rank < 4 or sv[-1] < 1e-9 * sv[0]:
        return centroid
    return centroid + sol[:3]


def _pose(origin: np.ndarray, rot: np.ndarray) -> np.ndarray:
    out = np.eye(4)
    out[:3, :3] = rot
    out[:3, 3] = origin
    return out


# --------------------------------------------------------------------------- charts
def _chart_error(projection: str, exc: GeometryError) -> GeometryError:
    """The chart's error; a degenerate chart suggests the other projections."""
    msg = f"{projection} chart: {exc}"
    if "degenerate" in str(exc):
        others = ", ".join(p for p in PROJECTIONS if p != projection)
        msg += (
            f"; the grasps do not spread out in the {projection} chart: try another "
            f"manifold.projection ({others})"
        )
    return GeometryError(msg)


def _triangulate(chart: np.ndarray, projection: str, triangulator: str) -> np.ndarray:
    try:
        return delaunay(chart, triangulator)
    except GeometryError as exc:
        raise _chart_error(projection, exc) from None


def _check_chart(chart: np.ndarray, projection: str) -> None:
    try:
        check_triangulable(chart)
    except GeometryError as exc:
        raise _chart_error(projection, exc) from None


def _approach_points(
    pos: np.ndarray, approach: np.ndarray, centre: np.ndarray, rot: np.ndarray, *, cyl: bool
) -> tuple[np.ndarray, np.ndarray]:
    """Chart-frame positions and the points that give each grasp its direction.

    Args:
        pos: (N, 3) world grasp positions.
        approach: (N, 3) world approach axes (grasp frame z, into the object).
        centre: (3,) chart origin.
        rot: (3, 3) chart axes (columns; z is the cylinder axis / pole direction).
        cyl: Cylindrical chart: drop the components along the axis (``_|_``).

    Returns:
        ``rel`` (N, 3), the positions in the chart frame, and ``v`` (N, 3), the
        points :data:`STANDOFF` back along the approach in the chart frame
        (their axial component zeroed when ``cyl``).
    """
    rel = (pos - centre) @ rot
    v = rel - STANDOFF * (approach @ rot)
    if cyl:
        v[:, 2] = 0.0
    return rel, v


def _chart_radius(standoff_dist: np.ndarray, projection: str) -> float:
    """Reference radius [m] of the chart: the median distance of the standoff points."""
    radius = float(np.median(standoff_dist))
    if not radius > 0:
        where = "axis" if projection == "cylindrical" else "centre"
        raise GeometryError(
            f"{projection} chart: the grasps' standoff points lie on the {where} (radius 0)"
        )
    return radius


def _cylindrical(
    pos: np.ndarray, approach: np.ndarray, frame: np.ndarray | None, triangulator: str
) -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
    if frame is not None:
        centre, rot = _frame_axes(frame)
    else:
        centre, axes = _principal_axes(pos)
        # Which principal axis: judged on the standoff points, which lie on a
        # cylinder even when the tool points crowd onto the axis (deep grasps).
        standoff = pos - STANDOFF * approach
        k = _cylinder_axis(standoff - standoff.mean(axis=0), axes)
        rot = np.column_stack((axes[:, (k + 1) % 3], axes[:, (k + 2) % 3], axes[:, k]))
    rel, v = _approach_points(pos, approach, centre, rot, cyl=True)
    theta = np.arctan2(v[:, 1], v[:, 0])
    theta[theta >= np.pi] -= 2 * np.pi
    radius = _chart_radius(np.hypot(v[:, 0], v[:, 1]), "cylindrical")
    chart = np.column_stack((radius * theta, rel[:, 2]))
    _check_chart(chart, "cylindrical")
    # Periodic triangulation: three copies one turn apart; tiny per-candidate
    # offsets (identical in every copy) break co-circular ties the same way.
    n = len(chart)
    turn = 2 * np.pi * radius
    extent = float(np.ptp(chart, axis=0).max())
    jitter = np.random.default_rng(0).uniform(-0.5, 0.5, (n, 2)) * (_JITTER * extent)
    base = chart + jitter
    ext = np.concatenate((base - (turn, 0.0), base, base + (turn, 0.0)))
    tris_ext = _triangulate(ext, "cylindrical", triangulator)
    ids = tris_ext % n
    xs = ext[tris_ext, 0]
    centroid = xs.mean(axis=1)
    # Area in the un-jittered chart: slivers along a straight top or bottom row
    # exist only because of the jitter and are not triangles of the mesh.
    raw = np.concatenate((chart - (turn, 0.0), chart, chart + (turn, 0.0)))[tris_ext]
    e1, e2 = raw[:, 1] - raw[:, 0], raw[:, 2] - raw[:, 0]
    area2 = e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0]
    keep = (
        (area2 > 1e-6 * extent * extent * _JITTER)
        & (centroid >= -0.5 * turn)
        & (centroid < 0.5 * turn)
        & (np.ptp(xs, axis=1) < 0.5 * turn)
        & (ids[:, 0] != ids[:, 1])
        & (ids[:, 1] != ids[:, 2])
        & (ids[:, 2] != ids[:, 0])
    )
    tris = ids[keep]
    _, first = np.unique(np.sort(tris, axis=1), axis=0, return_index=True)
    return chart, tris[np.sort(first)], _pose(centre, rot), turn


def _spherical(
    pos: np.ndarray, approach: np.ndarray, frame: np.ndarray | None, triangulator: str
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    if frame is not None:
        centre, rot = _frame_axes(frame)
    else:
        centre = _sphere_centre(pos)
        mean_dir = (pos - centre).sum(axis=0)
        if np.linalg.norm(mean_dir) < 1e-12 * max(float(np.abs(pos - centre).max()), 1e-300):
            _, axes = _principal_axes(pos)
            mean_dir = axes[:, 2]
        rot = _basis_from_axis(mean_dir)
    _, v = _approach_points(pos, approach, centre, rot, cyl=False)
    vdist = np.linalg.norm(v, axis=1)
    if (vdist <= 0).any():
        raise GeometryError(
            f"spherical chart: grasp {int(np.argmax(vdist <= 0))} is at the centre of the chart"
        )
    radius = _chart_radius(vdist, "spherical")
    u = v / vdist[:, None]
    denom = 1.0 + u[:, 2]
    bad = denom < 1e-9
    if bad.any():
        raise GeometryError(
            f"spherical chart: grasp {int(np.argmax(bad))} lies at the projection pole "
            "(straight below the centre)"
        )
    chart = 2.0 * radius * u[:, :2] / denom[:, None]
    return chart, _triangulate(chart, "spherical", triangulator), _pose(centre, rot)


def _planar(
    pos: np.ndarray, projection: str, triangulator: str
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    if projection == "xy":
        chart = pos[:, :2].copy()
        frame = np.eye(4)
    else:
        centre, axes = _principal_axes(pos)
        chart = (pos - centre) @ axes[:, :2]
        frame = _pose(centre, axes)
    return chart, _triangulate(chart, projection, triangulator), frame


def chart_triangles(
    pos: np.ndarray,
    approach: np.ndarray,
    projection: str,
    triangulator: str,
    frame: np.ndarray | None,
    same: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray | None, float | None]:
    """Chart and triangulate grasp positions (see the module docstring).

    Args:
        pos: (N, 3) grasp positions [m] (world).
        approach: (N, 3) approach axes (grasp frame z).
        projection: One of :data:`PROJECTIONS` (trusted).
        triangulator: ``qhull`` or ``bowyer_watson`` (trusted).
        frame: (4, 4) object frame for the cylindrical and spherical charts, or None.
        same: (N,) the first row of each row's pose (exact and near repeats,
            :func:`~gcm_pipeline.manifold.repeats.same_pose_rows`), or None
            (all distinct). The chart is made over the first rows, each
            once; a repeat takes its first row's chart point and is in no
            triangle (a million copies of a pose would be a million
            vertices, their triangles slivers).

    Returns:
        ``(chart (N, 2), triangles (T, 3), frame, period)``: the frame the
        chart used (None for ``xy``) and the period [m] of the cylindrical
        chart's first coordinate (None for the others).

    Raises:
        GeometryError: A non-rigid frame, or candidates all duplicate or
            collinear in the chart.
    """
    n = len(pos)
    kept = None if same is None else np.flatnonzero(same == np.arange(n))
    if kept is None or len(kept) == n:
        return _chart_triangles(pos, approach, projection, triangulator, frame)
    if len(kept) < 3:
        many = GeometryError(
            f"points are degenerate: only {len(kept)} distinct of {n} (all duplicates)"
        )
        raise _chart_error(projection, many)
    chart, tris, used_frame, period = _chart_triangles(
        pos[kept], approach[kept], projection, triangulator, frame
    )
    return chart[np.searchsorted(kept, same)], kept[tris], used_frame, period


def _chart_triangles(
    pos: np.ndarray,
    approach: np.ndarray,
    projection: str,
    triangulator: str,
    frame: np.ndarray | None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray | None, float | None]:
    """:func:`chart_triangles` over rows of which no two are one pose."""
    if projection == "cylindrical":
        return _cylindrical(pos, approach, frame, triangulator)
    if projection == "spherical":
        chart, tris, used_frame = _spherical(pos, approach, frame, triangulator)
    else:
        chart, tris, used_frame = _planar(pos, projection, triangulator)
    return chart, tris, used_frame, None
