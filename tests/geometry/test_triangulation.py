"""Delaunay triangulation: Qhull and the paper's Bowyer-Watson agree and are Delaunay."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial import ConvexHull

from gcm_pipeline.errors import GeometryError
from gcm_pipeline.geometry.bowyer_watson import bowyer_watson, delaunay

METHODS = ("qhull", "bowyer_watson")


def as_set(tris: np.ndarray) -> set[tuple[int, ...]]:
    return {tuple(t) for t in np.sort(tris, axis=1).tolist()}


def signed_areas(pts: np.ndarray, tris: np.ndarray) -> np.ndarray:
    a, b, c = pts[tris[:, 0]], pts[tris[:, 1]], pts[tris[:, 2]]
    return 0.5 * (
        (b[:, 0] - a[:, 0]) * (c[:, 1] - a[:, 1]) - (b[:, 1] - a[:, 1]) * (c[:, 0] - a[:, 0])
    )


def circumcircle_violations(pts: np.ndarray, tris: np.ndarray, rel_tol: float = 1e-9) -> int:
    """Number of (triangle, point) pairs with the point strictly inside the circumcircle."""
    a, b, c = pts[tris[:, 0]], pts[tris[:, 1]], pts[tris[:, 2]]
    d = 2 * (
        (a[:, 0] * (b[:, 1] - c[:, 1]))
        + b[:, 0] * (c[:, 1] - a[:, 1])
        + c[:, 0] * (a[:, 1] - b[:, 1])
    )
    a2, b2, c2 = (a**2).sum(1), (b**2).sum(1), (c**2).sum(1)
    ux = (a2 * (b[:, 1] - c[:, 1]) + b2 * (c[:, 1] - a[:, 1]) + c2 * (a[:, 1] - b[:, 1])) / d
    uy = (a2 * (c[:, 0] - b[:, 0]) + b2 * (a[:, 0] - c[:, 0]) + c2 * (b[:, 0] - a[:, 0])) / d
    centre = np.column_stack((ux, uy))
    r2 = ((a - centre) ** 2).sum(1)
    dist2 = ((pts[None, :, :] - centre[:, None, :]) ** 2).sum(2)
    inside = dist2 < r2[:, None] * (1 - rel_tol)
    return int(inside.sum())


def assert_valid(pts: np.ndarray, tris: np.ndarray, distinct: int | None = None) -> None:
    """Counter-clockwise, non-overlapping, covering the convex hull, using every point."""
    assert tris.dtype.kind == "i" and tris.shape[1] == 3
    areas = signed_areas(pts, tris)
    assert (areas > 0).all()
    hull = ConvexHull(pts).volume
    assert areas.sum() == pytest.approx(hull, rel=1e-9)
    used = np.unique(tris)
    if distinct is not None:
        assert len(used) == distinct
    assert as_set(tris).__len__() == len(tris)


@pytest.mark.parametrize("n", [3, 4, 10, 100, 1000])
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_qhull_and_bowyer_watson_agree_in_general_position(n, seed):
    pts = np.random.default_rng(seed).random((n, 2))
    q = delaunay(pts, "qhull")
    bw = delaunay(pts, "bowyer_watson")
    assert as_set(q) == as_set(bw)
    for tris in (q, bw):
        assert_valid(pts, tris, distinct=n)


@pytest.mark.parametrize("method", METHODS)
def test_empty_circumcircle_property(method):
    pts = np.random.default_rng(7).normal(size=(400, 2))
    tris = delaunay(pts, method)
    assert circumcircle_violations(pts, tris) == 0


def test_default_method_is_qhull_and_bowyer_watson_is_exposed():
    pts = np.random.default_rng(3).random((50, 2))
    np.testing.assert_array_equal(delaunay(pts), delaunay(pts, "qhull"))
    np.testing.assert_array_equal(bowyer_watson(pts), delaunay(pts, "bowyer_watson"))


def test_bowyer_watson_does_not_depend_on_insertion_order():
    pts = np.random.default_rng(4).random((500, 2))
    ref = as_set(bowyer_watson(pts, seed=0))
    assert as_set(bowyer_watson(pts, seed=1)) == ref
    assert as_set(bowyer_watson(pts, seed=99)) == ref


@pytest.mark.parametrize("method", METHODS)
def test_cocircular_grid_is_triangulated_consistently(method):
    gx, gy = np.meshgrid(np.arange(12.0), np.arange(7.0))
    pts = np.column_stack((gx.ravel(), gy.ravel()))
    tris = delaunay(pts, method)
    assert len(tris) == 2 * 11 * 6
    assert_valid(pts, tris, distinct=len(pts))
    assert circumcircle_violations(pts, tris) == 0


@pytest.mark.parametrize("method", METHODS)
def test_points_on_a_circle_and_collinear_hull_points(method):
    th = np.linspace(0, 2 * np.pi, 40, endpoint=False)
    circle = np.column_stack((np.cos(th), np.sin(th)))
    line = np.column_stack((np.linspace(-2, 2, 15), np.full(15, -2.0)))
    pts = np.vstack((circle, [[0.0, 0.0]], line))
    tris = delaunay(pts, method)
    assert_valid(pts, tris, distinct=len(pts))
    assert circumcircle_violations(pts, tris) == 0


@pytest.mark.parametrize("method", METHODS)
def test_duplicates_are_skipped_first_occurrence_used(method):
    rng = np.random.default_rng(5)
    pts = rng.random((30, 2))
    dup = np.vstack((pts, pts[[3, 7, 7]]))
    tris = delaunay(dup, method)
    assert tris.max() < 30
    assert as_set(tris) == as_set(delaunay(pts, method))


@pytest.mark.parametrize("method", METHODS)
def test_scale_and_offset_invariance(method):
    """Far from the origin and tiny: the uniform normalisation keeps the predicates exact enough."""
    pts = np.random.default_rng(6).random((300, 2))
    ref = as_set(delaunay(pts, method))
    assert as_set(delaunay(1e6 + 1e-3 * pts, method)) == ref
    assert as_set(delaunay(-5e3 + 1e4 * pts, method)) == ref


def test_non_uniform_scaling_is_not_applied():
    """Circles must stay circles: x and y are scaled by the same factor."""
    pts = np.random.default_rng(8).random((200, 2)) * [100.0, 1.0]
    for method in METHODS:
        assert circumcircle_violations(pts, delaunay(pts, method)) == 0


@settings(max_examples=60, deadline=None, derandomize=True)
@given(
    st.lists(st.tuples(st.integers(0, 6), st.integers(0, 6)), min_size=3, max_size=40, unique=True)
)
def test_bowyer_watson_on_degenerate_integer_points(coords):
    """Small integer grids: many collinear and co-circular points."""
    pts = np.array(coords, dtype=float)
    rank = np.linalg.matrix_rank(pts[1:] - pts[0])
    if rank < 2:
        with pytest.raises(GeometryError, match="collinear"):
            bowyer_watson(pts)
        return
    tris = bowyer_watson(pts)
    assert_valid(pts, tris, distinct=len(pts))
    assert circumcircle_violations(pts, tris) == 0
    assert len(tris) == len(delaunay(pts, "qhull"))


# ----------------------------------------------------------------------------- errors
@pytest.mark.parametrize("method", METHODS)
def test_error_fewer_than_three_points(method):
    with pytest.raises(GeometryError, match=r"at least 3 points to triangulate, got 2"):
        delaunay(np.zeros((2, 2)), method)


@pytest.mark.parametrize("method", METHODS)
def test_error_all_duplicates(method):
    with pytest.raises(GeometryError, match=r"only 2 distinct of 5 \(all duplicates\)"):
        delaunay([[0, 0], [1, 1], [0, 0], [1, 1], [0, 0]], method)


@pytest.mark.parametrize("method", METHODS)
def test_error_collinear(method):
    t = np.linspace(0, 1, 10)
    with pytest.raises(GeometryError, match=r"all 10 distinct points are collinear"):
        delaunay(np.column_stack((t, 2 * t + 1)), method)


@pytest.mark.parametrize("method", METHODS)
def test_error_non_finite_names_the_row(method):
    pts = np.random.default_rng(0).random((6, 2))
    pts[4, 1] = np.inf
    with pytest.raises(GeometryError, match=r"non-finite values at row 4"):
        delaunay(pts, method)


def test_error_shape():
    with pytest.raises(GeometryError, match=r"shape \(N, 2\), got \(4, 3\)"):
        delaunay(np.zeros((4, 3)))


def test_error_unknown_method_lists_valid_ones():
    with pytest.raises(
        GeometryError,
        match=r"unknown triangulator 'bowyer-watson' \(did you mean 'bowyer_watson'\?\); "
        r"valid: bowyer_watson, qhull",
    ):
        delaunay(np.random.default_rng(0).random((5, 2)), "bowyer-watson")


def test_hilbert_order_visits_grid_neighbours():
    """The insertion order's space-filling curve: each cell follows an adjacent one."""
    from gcm_pipeline.geometry.bowyer_watson import _hilbert_index

    n = 5
    gx, gy = np.meshgrid(np.arange(2**n), np.arange(2**n))
    d = _hilbert_index(gx.ravel(), gy.ravel(), order=n)
    assert sorted(d.tolist()) == list(range(4**n))
    cells = np.column_stack((gx.ravel(), gy.ravel()))[np.argsort(d)]
    assert (np.abs(np.diff(cells, axis=0)).sum(axis=1) == 1).all()
