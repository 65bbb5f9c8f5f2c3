"""Manifold stage: charts, seam closure, pruning, the Manifold object and errors."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from gcm_pipeline.errors import GcmError, GeometryError, InputError
from gcm_pipeline.geometry.bowyer_watson import delaunay
from gcm_pipeline.geometry.dualquat import (
    dq_from_matrix,
    dq_from_pos_quat,
    dq_mul,
    dq_to_matrix,
    dq_translation,
)
from gcm_pipeline.manifold.build import Manifold, build_manifold
from gcm_pipeline.manifold.charts import STANDOFF
from gcm_pipeline.table import GraspTable

IDENT = np.array([1.0, 0.0, 0.0, 0.0])


def table(dq: np.ndarray) -> GraspTable:
    return GraspTable({"dq": dq})


def plane_grasps(n: int = 40, seed: int = 0, yaw_deg: float = 10.0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    pos = np.column_stack((rng.uniform(0.3, 0.6, n), rng.uniform(-0.2, 0.2, n), np.full(n, 0.1)))
    rot = Rotation.from_euler(
        "xz", np.column_stack((np.full(n, 180.0), rng.uniform(-yaw_deg, yaw_deg, n))), degrees=True
    )
    xyzw = rot.as_quat()
    return dq_from_pos_quat(pos, np.column_stack((xyzw[:, 3], xyzw[:, :3])))


def cylinder_grasps(
    angles: int = 12,
    heights: int = 4,
    radius: float = 0.04,
    centre=(0.5, 0.0, 0.0),
    noise: float = 0.0,
    offset: float = 0.0,
    seed: int = 0,
    frame: np.ndarray | None = None,
    position_noise: float = 0.0,
) -> np.ndarray:
    """Radial side grasps on a grid of angles x heights (x along the axis, z toward it).

    ``radius`` is the tool points' distance from the axis (the object's radius
    minus the grasp depth); ``position_noise`` [m] moves each tool point by a
    Gaussian offset (orientations unchanged).
    """
    rng = np.random.default_rng(seed)
    a, h = np.meshgrid(
        offset + np.arange(angles) * 2 * np.pi / angles, np.linspace(0.02, 0.2, heights)
    )
    a = a.ravel() + noise * rng.normal(size=a.size)
    h = h.ravel() + noise * rng.normal(size=h.size)
    radial = np.column_stack((np.cos(a), np.sin(a), np.zeros_like(a)))
    m = np.zeros((a.size, 4, 4))
    m[:, :3, 0] = [0.0, 0.0, 1.0]
    m[:, :3, 2] = -radial
    m[:, :3, 1] = np.cross(m[:, :3, 2], m[:, :3, 0])
    m[:, :3, 3] = radius * radial + h[:, None] * [0.0, 0.0, 1.0]
    m[:, :3, 3] += position_noise * rng.normal(size=(a.size, 3))
    m[:, 3, 3] = 1.0
    if frame is None:
        frame = np.eye(4)
        frame[:3, 3] = centre
    return dq_from_matrix(frame @ m)


def object_frame(centre=(0.5, 0.0, 0.0), rotvec=(0.0, 0.0, 0.0)) -> np.ndarray:
    f = np.eye(4)
    f[:3, :3] = Rotation.from_rotvec(rotvec).as_matrix()
    f[:3, 3] = centre
    return f


def angular_span(manifold: Manifold, n_angles: int, heights: int) -> np.ndarray:
    """Per triangle, the number of angular grid steps it spans (wrapping)."""
    col = manifold.triangles % n_angles
    d = np.abs(col[:, :, None] - col[:, None, :])
    d = np.minimum(d, n_angles - d)
    return d.max(axis=(1, 2))


# ----------------------------------------------------------------------------- xy / pca
@pytest.mark.parametrize("triangulator", ["qhull", "bowyer_watson"])
def test_xy_chart_is_the_papers_projection(triangulator):
    dq = plane_grasps()
    m = build_manifold(table(dq), triangulator=triangulator)
    np.testing.assert_allclose(m.chart, dq_translation(dq)[:, :2])
    assert m.projection == "xy" and m.triangulator == triangulator
    assert m.triangles.dtype == np.int64 and m.triangles.shape[1] == 3
    assert {tuple(t) for t in np.sort(m.triangles, 1)} == {
        tuple(t) for t in np.sort(delaunay(m.chart), 1)
    }
    assert len(m.unused) == 0 and len(m.dropped) == 0
    a, b, c = (m.chart[m.triangles[:, k]] for k in range(3))
    e1, e2 = b - a, c - a
    assert (e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0] > 0).all()


def test_pca_chart_preserves_distances_of_a_tilted_plane():
    rng = np.random.default_rng(1)
    local = np.column_stack((rng.uniform(-0.1, 0.1, (30, 2)), np.zeros(30)))
    rot = Rotation.from_rotvec([0.7, -0.4, 0.2]).as_matrix()
    pos = local @ rot.T + [0.4, 0.1, 0.3]
    m = build_manifold(table(dq_from_pos_quat(pos, IDENT)), projection="pca")
    d_chart = np.linalg.norm(m.chart[:, None] - m.chart[None], axis=2)
    d_world = np.linalg.norm(pos[:, None] - pos[None], axis=2)
    np.testing.assert_allclose(d_chart, d_world, atol=1e-12)
    assert len(m.unused) == 0
    # xy of the same (steep) plane squashes it but still triangulates
    assert len(build_manifold(table(dq_from_pos_quat(pos, IDENT))).triangles) > 0


def test_same_xy_different_z_collapses_in_xy_but_not_cylindrical():
    """The paper's known problem: stacked grasps share one xy point."""
    dq = cylinder_grasps(angles=8, heights=3)
    xy = build_manifold(table(dq), projection="xy")
    assert len(xy.unused) == 8 * 2  # only the first of each column is a vertex
    cyl = build_manifold(table(dq), projection="cylindrical", frame=object_frame())
    assert len(cyl.unused) == 0


# ----------------------------------------------------------------------------- cylindrical
@pytest.mark.parametrize("triangulator", ["qhull", "bowyer_watson"])
@pytest.mark.parametrize("with_frame", [True, False])
@pytest.mark.parametrize("offset", [0.0, 0.13, np.pi / 12])
def test_cylindrical_mesh_closes_around_the_object(triangulator, with_frame, offset):
    n_a, n_h = 12, 4
    dq = cylinder_grasps(n_a, n_h, offset=offset)
    m = build_manifold(
        table(dq),
        projection="cylindrical",
        triangulator=triangulator,
        frame=object_frame() if with_frame else None,
    )
    # A closed band: every quad of the angle x height grid is two triangles,
    # including the quads across the +-pi seam; nothing spans more than one step.
    assert len(m.triangles) == n_a * (n_h - 1) * 2
    assert angular_span(m, n_a, n_h).max() == 1
    assert len(m.unused) == 0
    # Every angular gap (i, i+1 mod n) is bridged by triangles.
    col = m.triangles % n_a
    for i in range(n_a):
        j = (i + 1) % n_a
        bridges = ((col == i).any(axis=1) & (col == j).any(axis=1)).sum()
        assert bridges == 2 * (n_h - 1)
    # Each mesh edge is shared by at most two triangles; the closed band has
    # boundary edges only along the top and bottom rings.
    edges = np.sort(
        np.concatenate([m.triangles[:, [0, 1]], m.triangles[:, [1, 2]], m.triangles[:, [2, 0]]]),
        axis=1,
    )
    _, counts = np.unique(edges, axis=0, return_counts=True)
    assert counts.max() == 2
    assert (counts == 1).sum() == 2 * n_a
    # Chart: arc length at the standoff points' median radius (tool point
    # radius + standoff for radial grasps) and the height along the axis.
    assert m.period == pytest.approx(2 * np.pi * (0.04 + STANDOFF))
    assert np.ptp(m.chart[:, 0]) < m.period
    if with_frame:
        np.testing.assert_allclose(
            np.sort(np.unique(m.chart[:, 1].round(9))), np.linspace(0.02, 0.2, n_h)
        )


@pytest.mark.parametrize("triangulator", ["qhull", "bowyer_watson"])
def test_cylindrical_axis_of_a_squat_grasp_set_without_frame(triangulator):
    """A wide, short ring of grasps: the axis is the ring's normal, not its largest spread."""
    frame = object_frame((0.3, -0.1, 0.05), (0.2, 0.0, 0.4))
    dq = cylinder_grasps(16, 2, radius=0.15, frame=frame)
    m = build_manifold(table(dq), projection="cylindrical", triangulator=triangulator)
    assert len(m.triangles) == 16 * 2
    assert angular_span(m, 16, 2).max() == 1
    axis = m.frame[:3, 2]
    assert abs(abs(axis @ frame[:3, 2]) - 1.0) < 1e-9


def test_blend_chart_unwraps_the_seam():
    m = build_manifold(
        table(cylinder_grasps(12, 3)), projection="cylindrical", frame=object_frame()
    )
    assert m.period == pytest.approx(2 * np.pi * (0.04 + STANDOFF))
    w = np.full((len(m.triangles), 3), 1.0 / 3.0)
    centroids = m.blend_chart(m.triangles, w)
    # every centroid lies between its triangle's columns: within one step of each vertex
    step = m.period / 12
    for tri, c in zip(m.triangles, centroids, strict=True):
        dx = np.abs(m.chart[tri, 0] - c[0])
        dx = np.minimum(dx, m.period - dx)
        assert dx.max() <= step + 1e-12
    assert (np.abs(centroids[:, 0]) <= m.period / 2).all()
    flat = build_manifold(table(cylinder_grasps(12, 3)), projection="pca")
    assert flat.period is None
    w_flat = np.full((len(flat.triangles), 3), 1.0 / 3.0)
    np.testing.assert_allclose(
        flat.blend_chart(flat.triangles, w_flat), flat.chart[flat.triangles].mean(axis=1)
    )


def test_cylindrical_with_noise_and_a_tilted_object_frame():
    frame = object_frame((0.4, 0.2, 0.1), (0.3, 0.5, 0.0))
    dq = cylinder_grasps(16, 5, noise=0.002, frame=frame)
    m = build_manifold(table(dq), projection="cylindrical", frame=frame, max_edge_length=0.06)
    assert angular_span(m, 16, 5).max() <= 4  # hull slivers along the noisy rims at most
    col = m.triangles % 16
    seam = ((col == 15).any(axis=1) & (col == 0).any(axis=1)).sum()
    assert seam >= 2 * 4  # the seam between the last and the first column is closed
    assert len(m.unused) == 0
    np.testing.assert_allclose(m.frame, frame)


BOTTLE_RADIUS = 0.035


@pytest.mark.parametrize("triangulator", ["qhull", "bowyer_watson"])
@pytest.mark.parametrize("with_frame", [True, False])
@pytest.mark.parametrize("depth", [0.0, 0.01, 0.025, 0.032, BOTTLE_RADIUS])
def test_cylindrical_band_of_deep_side_grasps(triangulator, with_frame, depth):
    """Side grasps deep in a thin bottle, down to tool points on the axis: the full band.

    The angles come from the approach, not from the noisy tool point near the
    axis, and the arc scale does not shrink with the depth.
    """
    n_a, n_h = 12, 5
    frame = object_frame((0.4, 0.2, 0.1), (0.3, 0.5, 0.0))
    dq = cylinder_grasps(
        n_a, n_h, radius=BOTTLE_RADIUS - depth, frame=frame, position_noise=0.001, seed=3
    )
    m = build_manifold(
        table(dq),
        projection="cylindrical",
        triangulator=triangulator,
        frame=frame if with_frame else None,
        max_edge_length=0.08,
        max_edge_angle_deg=45.0,
    )
    assert len(m.triangles) == n_a * (n_h - 1) * 2  # as many as the shallow grid
    assert len(m.unused) == 0
    # dropped: only slivers along the noisy top and bottom rims (one ring each)
    ring = m.dropped // n_a
    assert (ring == ring[:, :1]).all() and np.isin(ring[:, 0], [0, n_h - 1]).all()
    assert angular_span(m, n_a, n_h).max() == 1
    col = m.triangles % n_a
    seam = ((col == n_a - 1).any(axis=1) & (col == 0).any(axis=1)).sum()
    assert seam == 2 * (n_h - 1)  # the seam is closed
    # one reference radius: the standoff points' median distance from the axis
    assert m.period == pytest.approx(2 * np.pi * (BOTTLE_RADIUS - depth + STANDOFF), abs=3e-3)
    assert abs(abs(m.frame[:3, 2] @ frame[:3, 2]) - 1.0) < 1e-4  # axis found without a frame
    # chart angle = the approach's angle about the axis (grid angle, +- the noise)
    theta = 2 * np.pi * m.chart[:, 0] / m.period
    grid = np.arange(n_a) * 2 * np.pi / n_a
    if with_frame:
        d = np.angle(np.exp(1j * (theta - np.tile(grid, n_h))))
        assert np.abs(d).max() < 0.05


@pytest.mark.parametrize("heights", [2, 3, 8])
def test_cylindrical_axis_without_frame_with_tool_points_on_the_axis(heights):
    """Positions scattered about the axis line: the standoff points pick the axis."""
    frame = object_frame((0.4, 0.2, 0.1), (0.3, 0.5, 0.0))
    for seed in range(20):
        dq = cylinder_grasps(12, heights, radius=0.0, frame=frame, position_noise=0.001, seed=seed)
        m = build_manifold(table(dq), projection="cylindrical", max_edge_angle_deg=45.0)
        assert abs(abs(m.frame[:3, 2] @ frame[:3, 2]) - 1.0) < 1e-3
        assert len(m.triangles) == 12 * (heights - 1) * 2  # (rim slivers dropped)


def test_cylindrical_top_grasps_keep_the_position_angle():
    """Grasps approached along the axis: the standoff point is straight above them."""
    n = 16
    ang = np.arange(n) * 2 * np.pi / n
    pos = np.column_stack((0.03 * np.cos(ang), 0.03 * np.sin(ang), np.tile([0.1, 0.12], n // 2)))
    m = np.tile(np.eye(4), (n, 1, 1))
    m[:, :3, :3] = np.diag([1.0, -1.0, -1.0])  # z (approach) straight down the axis
    m[:, :3, 3] = pos
    man = build_manifold(table(dq_from_matrix(m)), projection="cylindrical", frame=np.eye(4))
    assert man.period == pytest.approx(2 * np.pi * 0.03)
    np.testing.assert_allclose(
        np.angle(np.exp(1j * (2 * np.pi * man.chart[:, 0] / man.period - ang))), 0.0, atol=1e-9
    )


# ----------------------------------------------------------------------------- spherical
def fibonacci_sphere_grasps(
    n: int = 80, radius: float = 0.05, max_polar_deg: float = 120.0
) -> np.ndarray:
    i = np.arange(n) + 0.5
    cos_polar = 1 - (1 - np.cos(np.deg2rad(max_polar_deg))) * i / n
    polar = np.arccos(cos_polar)
    az = np.pi * (1 + 5**0.5) * i
    u = np.column_stack((np.sin(polar) * np.cos(az), np.sin(polar) * np.sin(az), np.cos(polar)))
    m = np.zeros((n, 4, 4))
    z = -u
    helper = np.where(np.abs(z[:, 2:3]) < 0.9, [[0.0, 0.0, 1.0]], [[1.0, 0.0, 0.0]])
    y = np.cross(z, helper)
    y /= np.linalg.norm(y, axis=1, keepdims=True)
    m[:, :3, 0], m[:, :3, 1], m[:, :3, 2] = np.cross(y, z), y, z
    m[:, :3, 3] = radius * u + [0.5, 0.0, 0.2]
    m[:, 3, 3] = 1.0
    return dq_from_matrix(m)


@pytest.mark.parametrize("triangulator", ["qhull", "bowyer_watson"])
@pytest.mark.parametrize("with_frame", [True, False])
def test_spherical_chart_gives_the_spherical_delaunay_mesh(triangulator, with_frame):
    dq = fibonacci_sphere_grasps()
    frame = object_frame((0.5, 0.0, 0.2)) if with_frame else None
    m = build_manifold(table(dq), projection="spherical", triangulator=triangulator, frame=frame)
    assert len(m.unused) == 0
    centre = np.array([0.5, 0.0, 0.2])  # found by the sphere fit without a frame
    np.testing.assert_allclose(m.frame[:3, 3], centre, atol=1e-12)
    u = dq_translation(dq) - centre
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    # Empty circumcircle on the sphere: all points on the inner side of each triangle's plane.
    a, b, c = (u[m.triangles[:, k]] for k in range(3))
    normal = np.cross(b - a, c - a)
    normal *= np.sign(np.einsum("ij,ij->i", normal, a))[:, None]
    assert (
        np.einsum("tj,nj->tn", normal, u) - np.einsum("tj,tj->t", normal, a)[:, None] <= 1e-12
    ).all()
    # A disc-like mesh: each edge in at most two triangles.
    edges = np.sort(
        np.concatenate([m.triangles[:, [0, 1]], m.triangles[:, [1, 2]], m.triangles[:, [2, 0]]]),
        axis=1,
    )
    assert np.unique(edges, axis=0, return_counts=True)[1].max() == 2


@pytest.mark.parametrize("depth", [0.02, 0.045, 0.05])
def test_spherical_chart_of_deep_grasps_keeps_the_shallow_mesh(depth):
    """Tool points near the sphere's centre: directions come from the approach."""
    centre = np.array([0.5, 0.0, 0.2])
    shallow = fibonacci_sphere_grasps()
    m = dq_to_matrix(shallow)
    rng = np.random.default_rng(0)
    m[:, :3, 3] = centre + (m[:, :3, 3] - centre) * (0.05 - depth) / 0.05
    m[:, :3, 3] += 1e-4 * rng.normal(size=(len(m), 3))
    frame = object_frame(centre)
    ref = build_manifold(table(shallow), projection="spherical", frame=frame)
    deep = build_manifold(table(dq_from_matrix(m)), projection="spherical", frame=frame)
    assert {tuple(t) for t in np.sort(deep.triangles, 1)} == {
        tuple(t) for t in np.sort(ref.triangles, 1)
    }
    # one scale: twice the standoff points' median distance from the centre
    scale = np.linalg.norm(deep.chart, axis=1) / np.linalg.norm(ref.chart, axis=1)
    np.testing.assert_allclose(scale, (0.05 - depth + STANDOFF) / (0.05 + STANDOFF), rtol=1e-2)


def test_spherical_error_grasp_at_the_pole():
    dq = fibonacci_sphere_grasps(20)
    pole = dq_from_pos_quat([0.5, 0.0, 0.2 - 0.05], IDENT)
    with pytest.raises(GeometryError, match=r"grasp 20 lies at the projection pole"):
        build_manifold(
            table(np.vstack((dq, pole))),
            projection="spherical",
            frame=object_frame((0.5, 0.0, 0.2)),
        )


# ----------------------------------------------------------------------------- pruning
def test_edge_length_drops_triangles_between_clusters():
    rng = np.random.default_rng(2)
    left = np.column_stack((rng.uniform(0, 0.05, (15, 2)), np.zeros(15)))
    right = left + [0.5, 0.0, 0.0]
    dq = dq_from_pos_quat(np.vstack((left, right)), IDENT)
    full = build_manifold(table(dq))
    m = build_manifold(table(dq), max_edge_length=0.1)
    pos = dq_translation(dq)
    p = pos[full.triangles]
    longest = np.linalg.norm(p - np.roll(p, -1, axis=1), axis=2).max(axis=1)
    assert len(m.dropped) == int((longest > 0.1).sum()) > 0
    assert len(m.triangles) + len(m.dropped) == len(full.triangles)
    assert set(m.dropped_reason.tolist()) == {"edge_length"}
    assert m.dropped_counts == {"edge_length": len(m.dropped)}
    crosses = (m.dropped < 15).any(axis=1) & (m.dropped >= 15).any(axis=1)
    assert crosses.all()
    assert not ((m.triangles < 15).any(axis=1) & (m.triangles >= 15).any(axis=1)).any()


def test_edge_angle_drops_triangles_with_twisted_vertices():
    dq = plane_grasps(40, yaw_deg=5.0)
    flipped = dq.copy()
    half = np.arange(40) % 2 == 1
    turn = dq_from_pos_quat([0.0, 0.0, 0.0], [np.cos(np.pi / 4), 0.0, 0.0, np.sin(np.pi / 4)])
    flipped[half] = dq_mul(dq[half], turn)  # 90 deg about the approach axis
    m = build_manifold(table(flipped), max_edge_angle_deg=45.0)
    full = build_manifold(table(flipped))
    mixed = half[full.triangles].any(axis=1) & ~half[full.triangles].all(axis=1)
    assert len(m.dropped) == int(mixed.sum()) > 0
    assert m.dropped_counts == {"edge_angle": int(mixed.sum())}
    # a generous threshold keeps them all
    assert len(build_manifold(table(flipped), max_edge_angle_deg=120.0).dropped) == 0


def test_edge_length_takes_precedence_over_edge_angle_in_the_reason():
    dq = dq_from_pos_quat(
        [[0, 0, 0], [1, 0, 0], [0, 1, 0]], [[1, 0, 0, 0], [0, 1, 0, 0], [1, 0, 0, 0]]
    )
    m = build_manifold(table(dq), max_edge_length=0.5, max_edge_angle_deg=10.0)
    assert m.dropped_reason.tolist() == ["edge_length"]
    assert m.triangles.shape == (0, 3)
    np.testing.assert_array_equal(m.unused, [0, 1, 2])


# ----------------------------------------------------------------------------- the object
def test_manifold_repr_counts_and_read_only_arrays():
    dq = plane_grasps(20)
    m = build_manifold(table(dq), max_edge_length=0.12)
    text = repr(m)
    assert text.startswith("Manifold(projection='xy', triangulator='qhull', 20 vertices, ")
    assert f"{len(m.triangles)} triangles" in text
    assert f"{len(m.dropped)} dropped" in text
    if len(m.dropped):
        assert "edge_length:" in text
    assert m.n_vertices == 20
    np.testing.assert_array_equal(m.vertex_ids, np.arange(20))
    with pytest.raises(dataclasses.FrozenInstanceError):
        m.projection = "pca"  # type: ignore[misc]
    with pytest.raises(ValueError):
        m.triangles[0, 0] = 5
    assert m.dropped.shape[1] == 3 and m.dropped_reason.dtype.kind == "U"


# ----------------------------------------------------------------------------- errors
def test_error_unknown_projection_lists_valid_ones():
    with pytest.raises(
        GeometryError,
        match=r"unknown projection 'cylinder' \(did you mean 'cylindrical'\?\); "
        r"valid: cylindrical, pca, spherical, xy",
    ):
        build_manifold(table(plane_grasps()), projection="cylinder")


def test_error_unknown_triangulator():
    with pytest.raises(
        GeometryError, match=r"unknown triangulator 'delaunay'; valid: bowyer_watson, qhull"
    ):
        build_manifold(table(plane_grasps()), triangulator="delaunay")


def test_error_fewer_than_three_poses():
    with pytest.raises(GeometryError, match=r"at least 3 grasp poses to build a manifold, got 2"):
        build_manifold(table(plane_grasps()[:2]))


def test_error_non_finite_pose_names_the_row():
    dq = plane_grasps()
    dq[7, 5] = np.nan
    with pytest.raises(GeometryError, match=r"non-finite values at row 7"):
        build_manifold(table(dq))


def test_error_missing_dq_column():
    with pytest.raises(InputError, match=r"no column 'dq'"):
        build_manifold(GraspTable({"x": np.zeros(4)}))


def test_error_all_duplicate_positions():
    dq = dq_from_pos_quat(np.tile([0.1, 0.2, 0.3], (5, 1)), IDENT)
    with pytest.raises(
        GeometryError, match=r"xy chart: points are degenerate: only 1 distinct of 5"
    ):
        build_manifold(table(dq))


def test_error_collinear_in_the_chart():
    t = np.linspace(0, 1, 6)
    dq = dq_from_pos_quat(np.column_stack((t, t, t)), IDENT)  # a line: collinear in xy
    with pytest.raises(GeometryError, match=r"xy chart: .*collinear"):
        build_manifold(table(dq))
    # one ring at one height is collinear in the cylindrical chart
    ring = cylinder_grasps(8, 1)
    with pytest.raises(GeometryError, match=r"cylindrical chart: .*collinear"):
        build_manifold(table(ring), projection="cylindrical", frame=object_frame())


def test_error_non_rigid_frame():
    frame = object_frame()
    frame[0, 0] = 2.0
    with pytest.raises(GeometryError, match=r"frame: rotation block .* not orthonormal"):
        build_manifold(table(cylinder_grasps()), projection="cylindrical", frame=frame)
    with pytest.raises(GeometryError, match=r"frame must be a \(4, 4\) pose"):
        build_manifold(table(cylinder_grasps()), projection="cylindrical", frame=np.eye(3))


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"max_edge_length": -0.1}, r"max_edge_length must be in \(0, inf\], got -0.1"),
        ({"max_edge_angle_deg": 0.0}, r"max_edge_angle_deg must be in \(0, 180\], got 0.0"),
        ({"max_edge_angle_deg": 200}, r"max_edge_angle_deg must be in \(0, 180\], got 200"),
    ],
)
def test_error_thresholds(kwargs, message):
    with pytest.raises(GcmError, match=message):
        build_manifold(table(plane_grasps()), **kwargs)
