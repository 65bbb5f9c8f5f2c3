"""Dual quaternion algebra, conversions, blends and their errors."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from poses import equal_up_to_sign, same_pose
from scipy.spatial.transform import Rotation

from gcm_pipeline.errors import GcmError, GeometryError
from gcm_pipeline.geometry.dualquat import (
    dq_angle_distance,
    dq_conj,
    dq_distance,
    dq_exp,
    dq_from_matrix,
    dq_from_pos_quat,
    dq_identity,
    dq_inv,
    dq_log,
    dq_mul,
    dq_normalize,
    dq_to_matrix,
    dq_to_pos_quat,
    dq_transform_points,
    dq_translation,
)
from gcm_pipeline.geometry.pose_blend import dib, dlb, sclerp

ATOL = 1e-12


def random_quat(rng: np.random.Generator, n: int) -> np.ndarray:
    q = rng.normal(size=(n, 4))
    return q / np.linalg.norm(q, axis=1, keepdims=True)


def random_dq(rng: np.random.Generator, n: int, scale: float = 1.0) -> np.ndarray:
    return dq_from_pos_quat(rng.normal(scale=scale, size=(n, 3)), random_quat(rng, n))


def random_matrices(rng: np.random.Generator, n: int) -> np.ndarray:
    m = np.zeros((n, 4, 4))
    m[:, :3, :3] = Rotation.random(n, random_state=rng).as_matrix()
    m[:, :3, 3] = rng.normal(size=(n, 3))
    m[:, 3, 3] = 1.0
    return m


def assert_unit(dq: np.ndarray) -> None:
    r, d = dq[..., :4], dq[..., 4:]
    np.testing.assert_allclose(np.linalg.norm(r, axis=-1), 1.0, atol=ATOL)
    np.testing.assert_allclose(np.einsum("...i,...i->...", r, d), 0.0, atol=ATOL)


@pytest.fixture
def rng() -> np.random.Generator:
    return np.random.default_rng(12345)


# ----------------------------------------------------------------------------- group axioms
def test_constructed_poses_are_unit(rng):
    assert_unit(random_dq(rng, 200, scale=5.0))
    assert_unit(dq_from_matrix(random_matrices(rng, 200)))


def test_product_closure_identity_inverse_associativity(rng):
    a, b, c = (random_dq(rng, 100) for _ in range(3))
    assert_unit(dq_mul(a, b))
    ident = dq_identity((100,))
    np.testing.assert_allclose(dq_mul(ident, a), a, atol=ATOL)
    np.testing.assert_allclose(dq_mul(a, ident), a, atol=ATOL)
    np.testing.assert_allclose(dq_mul(a, dq_inv(a)), ident, atol=ATOL)
    np.testing.assert_allclose(dq_mul(dq_inv(a), a), ident, atol=ATOL)
    np.testing.assert_allclose(dq_conj(a), dq_inv(a), atol=ATOL)
    np.testing.assert_allclose(dq_mul(dq_mul(a, b), c), dq_mul(a, dq_mul(b, c)), atol=ATOL)


def test_product_is_matrix_composition(rng):
    a, b = random_dq(rng, 50), random_dq(rng, 50)
    np.testing.assert_allclose(
        dq_to_matrix(dq_mul(a, b)), dq_to_matrix(a) @ dq_to_matrix(b), atol=ATOL
    )


def test_inverse_of_non_unit_input(rng):
    a = random_dq(rng, 20) * rng.uniform(0.5, 2.0, size=(20, 1))
    np.testing.assert_allclose(dq_mul(a, dq_inv(a)), dq_identity((20,)), atol=ATOL)


def test_normalize_projects_to_unit_keeping_the_pose(rng):
    a = random_dq(rng, 50)
    noisy = a * rng.uniform(0.5, 2.0, size=(50, 1))
    noisy[:, 4:] += 0.3 * noisy[:, :4]  # a dual part parallel to r carries no pose
    out = dq_normalize(noisy)
    assert_unit(out)
    np.testing.assert_allclose(out, a, atol=ATOL)


# ----------------------------------------------------------------------------- conversions
def test_matrix_round_trip(rng):
    m = random_matrices(rng, 300)
    dq = dq_from_matrix(m)
    assert (dq[:, 0] >= 0).all()
    np.testing.assert_allclose(dq_to_matrix(dq), m, atol=ATOL)
    np.testing.assert_allclose(dq_from_matrix(dq_to_matrix(dq)), dq, atol=ATOL)


def test_matrix_to_dq_matches_scipy_in_wxyz_order(rng):
    m = random_matrices(rng, 100)
    xyzw = Rotation.from_matrix(m[:, :3, :3]).as_quat()
    wxyz = np.column_stack((xyzw[:, 3], xyzw[:, :3]))
    assert equal_up_to_sign(dq_from_matrix(m)[:, :4], wxyz)
    np.testing.assert_allclose(dq_translation(dq_from_matrix(m)), m[:, :3, 3], atol=ATOL)


def test_matrix_conversion_handles_half_turns():
    """Rotations by pi (w = 0) are where naive trace formulas fail."""
    for axis in np.eye(3):
        m = np.eye(4)
        m[:3, :3] = Rotation.from_rotvec(np.pi * axis).as_matrix()
        m[:3, 3] = [1.0, -2.0, 0.5]
        np.testing.assert_allclose(dq_to_matrix(dq_from_matrix(m)), m, atol=ATOL)


def test_batch_shapes_are_kept(rng):
    m = random_matrices(rng, 24).reshape(2, 3, 4, 4, 4)
    dq = dq_from_matrix(m)
    assert dq.shape == (2, 3, 4, 8)
    assert dq_to_matrix(dq).shape == (2, 3, 4, 4, 4)
    assert dq_from_matrix(np.eye(4)).shape == (8,)
    np.testing.assert_array_equal(dq_from_matrix(np.eye(4)), dq_identity())


def test_pos_quat_round_trip_and_wxyz_convention(rng):
    pos = rng.normal(size=(100, 3))
    quat = random_quat(rng, 100)
    dq = dq_from_pos_quat(pos, quat)
    p2, q2 = dq_to_pos_quat(dq)
    np.testing.assert_allclose(p2, pos, atol=ATOL)
    np.testing.assert_allclose(q2, quat, atol=ATOL)
    xyzw = np.column_stack((quat[:, 1:], quat[:, 0]))
    np.testing.assert_allclose(
        dq_to_matrix(dq)[:, :3, :3], Rotation.from_quat(xyzw).as_matrix(), atol=ATOL
    )


def test_pos_quat_normalises_quaternions_and_broadcasts():
    dq = dq_from_pos_quat(np.zeros((5, 3)), [2.0, 0.0, 0.0, 0.0])
    np.testing.assert_array_equal(dq, dq_identity((5,)))


def test_standard_convention_dual_part():
    """d = 0.5 (0, t) r: a pure translation has dual part (0, t/2)."""
    dq = dq_from_pos_quat([0.2, -0.4, 0.6], [1.0, 0.0, 0.0, 0.0])
    np.testing.assert_allclose(dq, [1, 0, 0, 0, 0, 0.1, -0.2, 0.3], atol=ATOL)


def test_point_transform_matches_matrix(rng):
    dq = random_dq(rng, 50)
    pts = rng.normal(size=(50, 3))
    m = dq_to_matrix(dq)
    expected = np.einsum("nij,nj->ni", m[:, :3, :3], pts) + m[:, :3, 3]
    np.testing.assert_allclose(dq_transform_points(dq, pts), expected, atol=ATOL)
    # one pose, many points
    many = dq_transform_points(dq[0], pts)
    np.testing.assert_allclose(many, pts @ m[0, :3, :3].T + m[0, :3, 3], atol=ATOL)


# ----------------------------------------------------------------------------- double cover
def test_double_cover_same_matrix(rng):
    dq = random_dq(rng, 50)
    np.testing.assert_allclose(dq_to_matrix(-dq), dq_to_matrix(dq), atol=ATOL)
    np.testing.assert_allclose(dq_angle_distance(dq, -dq), 0.0, atol=1e-7)


def test_dlb_of_antipodal_copies_does_not_cancel(rng):
    q = random_dq(rng, 30)
    pair = np.stack((q, -q), axis=1)
    for pivot in ("heaviest", "first"):
        out = dlb(pair, [0.5, 0.5], pivot=pivot)
        assert_unit(out)
        assert same_pose(out, q)


def test_dlb_sign_alignment_makes_signs_irrelevant(rng):
    q = random_dq(rng, 3 * 40, scale=0.1).reshape(40, 3, 8)
    w = rng.dirichlet([1.0, 1.0, 1.0], size=40)
    flips = rng.choice([-1.0, 1.0], size=(40, 3, 1))
    for pivot in ("heaviest", "first"):
        assert same_pose(dlb(q * flips, w, pivot=pivot), dlb(q, w, pivot=pivot))
    # The result is sign-aligned with the pivot (the heaviest pose).
    piv = q[np.arange(40), np.argmax(w, axis=1)]
    assert (np.einsum("ni,ni->n", dlb(q, w)[:, :4], piv[:, :4]) > 0).all()


# ----------------------------------------------------------------------------- distances
def test_distances_known_values():
    a = dq_from_pos_quat([0, 0, 0], [1, 0, 0, 0])
    rot = Rotation.from_rotvec([0, 0, 0.3]).as_quat()
    b = dq_from_pos_quat([3.0, 4.0, 0.0], np.r_[rot[3], rot[:3]])
    dist, ang = dq_distance(a, b)
    assert dist == pytest.approx(5.0)
    assert ang == pytest.approx(0.3)
    big = Rotation.from_rotvec([0, 2.5, 0]).as_quat()
    c = dq_from_pos_quat([0, 0, 0], np.r_[big[3], big[:3]])
    assert dq_angle_distance(a, c) == pytest.approx(2.5)
    assert dq_angle_distance(a, -c) == pytest.approx(2.5)


def test_distances_are_batched(rng):
    a, b = random_dq(rng, 12).reshape(3, 4, 8), random_dq(rng, 12).reshape(3, 4, 8)
    d, ang = dq_distance(a, b)
    assert d.shape == ang.shape == (3, 4)
    assert (ang >= 0).all() and (ang <= np.pi + 1e-12).all()


# ----------------------------------------------------------------------------- log / exp
def test_log_exp_round_trip(rng):
    dq = random_dq(rng, 200)
    xi = dq_log(dq)
    assert np.linalg.norm(xi[:, :3], axis=1).max() <= np.pi + 1e-12
    assert same_pose(dq_exp(xi), dq)


@pytest.mark.parametrize("angle", [0.0, 1e-9, 1e-5, 1e-3, 0.5, np.pi - 1e-6, np.pi])
def test_log_exp_near_special_angles(angle):
    rotvec = angle * np.array([0.6, 0.0, 0.8])
    xyzw = Rotation.from_rotvec(rotvec).as_quat()
    dq = dq_from_pos_quat([0.3, -0.1, 0.2], np.r_[xyzw[3], xyzw[:3]])
    assert same_pose(dq_exp(dq_log(dq)), dq, atol=1e-12)
    np.testing.assert_allclose(np.linalg.norm(dq_log(dq)[:3]), angle, atol=1e-9)


def test_log_of_pure_translation_is_the_translation():
    dq = dq_from_pos_quat([0.1, 0.2, 0.3], [1, 0, 0, 0])
    np.testing.assert_allclose(dq_log(dq), [0, 0, 0, 0.1, 0.2, 0.3], atol=ATOL)


# ----------------------------------------------------------------------------- ScLERP / DLB / DIB
def test_dlb_and_sclerp_endpoints(rng):
    a, b = random_dq(rng, 40), random_dq(rng, 40)
    pair = np.stack((a, b), axis=1)
    assert same_pose(dlb(pair, [1.0, 0.0]), a)
    assert same_pose(dlb(pair, [0.0, 1.0]), b)
    assert same_pose(sclerp(a, b, 0.0), a)
    assert same_pose(sclerp(a, b, 1.0), b)


@pytest.mark.parametrize("t", [0.0, 0.2, 0.5, 0.9, 1.0])
def test_dlb_equals_sclerp_on_pure_translations(rng, t):
    ident = np.array([1.0, 0.0, 0.0, 0.0])
    a = dq_from_pos_quat(rng.normal(size=(20, 3)), ident)
    b = dq_from_pos_quat(rng.normal(size=(20, 3)), ident)
    blended = dlb(np.stack((a, b), axis=1), [1 - t, t])
    np.testing.assert_allclose(blended, sclerp(a, b, t), atol=ATOL)
    np.testing.assert_allclose(
        dq_translation(blended), (1 - t) * dq_translation(a) + t * dq_translation(b), atol=ATOL
    )


def _rotation_about_line(angle: float, axis: np.ndarray, point: np.ndarray) -> np.ndarray:
    """Pose of a rotation by ``angle`` about the line through ``point`` along ``axis``."""
    m = np.eye(4)
    m[:3, :3] = Rotation.from_rotvec(angle * axis).as_matrix()
    m[:3, 3] = point - m[:3, :3] @ point
    return dq_from_matrix(m)


def test_dlb_and_sclerp_on_rotations_about_a_fixed_line():
    """Same line, angles a1, a2: DLB keeps the line at any t; equals ScLERP at t = 1/2.

    DLB's angle b satisfies tan(b/2) = sum w sin(a/2) / sum w cos(a/2): the mean
    angle for equal weights only, so ScLERP (linear in the angle) agrees
    exactly at t = 1/2 and not elsewhere.
    """
    axis = np.array([1.0, 2.0, 2.0]) / 3.0
    point = np.array([0.5, -0.2, 0.1])
    a = _rotation_about_line(0.2, axis, point)
    b = _rotation_about_line(1.9, axis, point)
    pair = np.stack((a, b))
    mid = dlb(pair, [0.5, 0.5])
    assert same_pose(mid, sclerp(a, b, 0.5), atol=1e-12)
    assert same_pose(mid, _rotation_about_line(1.05, axis, point), atol=1e-12)
    for t in (0.1, 0.3, 0.8):
        blended = dlb(pair, [1 - t, t])
        on_line = point + np.array([[0.0], [1.0], [-2.0]]) * axis
        np.testing.assert_allclose(dq_transform_points(blended, on_line), on_line, atol=1e-12)
        angle = 2 * np.arctan2(
            (1 - t) * np.sin(0.1) + t * np.sin(0.95), (1 - t) * np.cos(0.1) + t * np.cos(0.95)
        )
        assert same_pose(blended, _rotation_about_line(angle, axis, point), atol=1e-12)
        assert not same_pose(blended, sclerp(a, b, t), atol=1e-6)


@settings(max_examples=40, deadline=None, derandomize=True)
@given(t=st.floats(0.0, 1.0), seed=st.integers(0, 2**31 - 1))
def test_dib_equals_sclerp_for_two_poses(t, seed):
    rng = np.random.default_rng(seed)
    a, b = random_dq(rng, 4), random_dq(rng, 4)
    out = dib(np.stack((a, b), axis=1), np.column_stack((np.full(4, 1 - t), np.full(4, t))))
    assert same_pose(out, sclerp(a, b, t), atol=1e-9)


def test_dib_is_bi_invariant_and_close_to_dlb_for_nearby_poses(rng):
    base = random_dq(rng, 1)
    near = dq_mul(base, dq_exp(0.1 * rng.normal(size=(30, 3, 6))))
    w = rng.dirichlet([1.0, 1.0, 1.0], size=30)
    mean = dib(near, w)
    left, right = random_dq(rng, 1), random_dq(rng, 1)
    moved = dq_mul(dq_mul(left, near), right)
    assert same_pose(dib(moved, w), dq_mul(dq_mul(left, mean), right), atol=1e-9)
    # The weighted log residual vanishes at the DIB mean.
    rel = dq_mul(dq_conj(mean)[:, None, :], near)
    np.testing.assert_allclose(np.einsum("nk,nkc->nc", w, dq_log(rel)), 0.0, atol=1e-10)
    d, ang = dq_distance(mean, dlb(near, w))
    assert d.max() < 1e-3 and ang.max() < 1e-3


def test_sclerp_is_a_constant_speed_screw(rng):
    a, b = random_dq(rng, 10), random_dq(rng, 10)
    ts = np.linspace(0, 1, 5)
    path = sclerp(a[:, None], b[:, None], ts[None, :])
    assert path.shape == (10, 5, 8)
    step = dq_angle_distance(path[:, :-1], path[:, 1:])
    np.testing.assert_allclose(step, step[:, :1].repeat(4, axis=1), atol=1e-9)


def test_dlb_weight_and_pose_batch_shapes(rng):
    poses = random_dq(rng, 4)
    w = rng.dirichlet(np.ones(4), size=(2, 5))
    out = dlb(poses, w)
    assert out.shape == (2, 5, 8)
    per_row = np.stack([dlb(poses, row) for row in w.reshape(-1, 4)]).reshape(2, 5, 8)
    np.testing.assert_allclose(out, per_row, atol=ATOL)
    batched = dlb(np.broadcast_to(poses, (2, 5, 4, 8)), w)
    np.testing.assert_allclose(batched, out, atol=ATOL)
    assert dlb(poses, [0.25] * 4).shape == (8,)


def test_dlb_one_hot_weights_reproduce_the_pose(rng):
    q = random_dq(rng, 3)
    for k in range(3):
        w = np.zeros(3)
        w[k] = 1.0
        np.testing.assert_allclose(dlb(q, w), q[k], atol=1e-15)


# ----------------------------------------------------------------------------- errors
def _matrix_batch() -> np.ndarray:
    m = np.tile(np.eye(4), (5, 1, 1))
    m[:, :3, 3] = np.arange(15.0).reshape(5, 3)
    return m


def test_error_non_finite_matrix():
    m = _matrix_batch()
    m[2, 0, 3] = np.nan
    with pytest.raises(GeometryError, match=r"non-finite values at index 2"):
        dq_from_matrix(m)


def test_error_not_orthonormal_names_first_bad_index():
    m = _matrix_batch()
    m[3, 0, 0] = 1.001
    m[4, 1, 1] = 2.0
    with pytest.raises(GeometryError, match=r"index 3 is not orthonormal"):
        dq_from_matrix(m)
    m = _matrix_batch()
    m[1, 0, 1] = 5e-7  # within tolerance
    dq_from_matrix(m)


def test_error_not_orthonormal_in_a_2d_batch():
    m = np.tile(np.eye(4), (2, 3, 1, 1))
    m[1, 2, :3, :3] *= 1.1
    with pytest.raises(GeometryError, match=r"index \(1, 2\)"):
        dq_from_matrix(m)


def test_error_non_rigid_bottom_row():
    m = _matrix_batch()
    m[1, 3, 0] = 0.5
    with pytest.raises(GeometryError, match=r"index 1 is not rigid: bottom row"):
        dq_from_matrix(m)


def test_error_reflection():
    m = _matrix_batch()
    m[0, 2, 2] = -1.0
    with pytest.raises(GeometryError, match=r"index 0 is a reflection"):
        dq_from_matrix(m)


def test_error_matrix_shape():
    with pytest.raises(GeometryError, match=r"shape \(\.\.\., 4, 4\), got \(3, 3\)"):
        dq_from_matrix(np.eye(3))


def test_error_zero_norm_quaternion():
    quat = np.tile([1.0, 0.0, 0.0, 0.0], (4, 1))
    quat[2] = 0.0
    with pytest.raises(GeometryError, match=r"quat has zero norm at index 2"):
        dq_from_pos_quat(np.zeros((4, 3)), quat)


def test_error_non_finite_position():
    pos = np.zeros((4, 3))
    pos[1, 2] = np.inf
    with pytest.raises(GeometryError, match=r"pos has non-finite values at index 1"):
        dq_from_pos_quat(pos, [1, 0, 0, 0])


def test_error_zero_norm_dual_quaternion():
    with pytest.raises(GeometryError, match=r"zero-norm rotation .* index 1"):
        dq_normalize(np.stack((dq_identity(), np.zeros(8))))


def test_error_dlb_weights(rng):
    q = random_dq(rng, 3)
    with pytest.raises(GeometryError, match=r"sum to 1, got 0\.9 at index 1"):
        dlb(q, [[0.2, 0.3, 0.5], [0.3, 0.3, 0.3]])
    with pytest.raises(GeometryError, match=r">= 0, got -0\.1 at index \(0, 2\)"):
        dlb(q, [[0.5, 0.6, -0.1]])
    dlb(q, [[0.5, 0.5 + 1e-10, -1e-10]])  # within 1e-9
    with pytest.raises(GeometryError, match=r"non-finite"):
        dlb(q, [np.nan, 0.5, 0.5])
    with pytest.raises(GeometryError, match=r"K = 3 poses"):
        dlb(q, [0.5, 0.5])
    with pytest.raises(GeometryError, match=r"unknown DLB pivot 'heavy'.*did you mean 'heaviest'"):
        dlb(q, [1.0, 0.0, 0.0], pivot="heavy")  # type: ignore[arg-type]
    with pytest.raises(GcmError, match=r"sum to 1"):
        dib(q, [0.5, 0.4, 0.0])


def test_error_dlb_non_finite_pose(rng):
    q = random_dq(rng, 3)
    q[1, 5] = np.nan
    with pytest.raises(GeometryError, match=r"dqs has non-finite values at index 1"):
        dlb(q, [0.2, 0.3, 0.5])


def test_error_sclerp_non_finite_t(rng):
    a, b = random_dq(rng, 2)
    with pytest.raises(GeometryError, match=r"non-finite"):
        sclerp(a, b, np.nan)


def test_dib_warns_when_not_converged(rng):
    q = random_dq(rng, 3)
    with pytest.warns(RuntimeWarning, match=r"DIB did not converge .* for 1 of 1 blends"):
        dib(q, [0.2, 0.3, 0.5], max_iter=1)


def test_quat_from_rotation_matches_scipy_and_dq_from_matrix() -> None:
    from gcm_pipeline.geometry.dualquat import quat_from_rotation

    rot = Rotation.random(200, random_state=7)
    q = quat_from_rotation(rot.as_matrix().reshape(10, 20, 3, 3))
    assert q.shape == (10, 20, 4) and np.all(q[..., 0] >= 0)
    want = rot.as_quat()[:, [3, 0, 1, 2]]
    want *= np.where(want[:, :1] < 0, -1.0, 1.0)
    np.testing.assert_allclose(q.reshape(-1, 4), want, atol=1e-12)
    m = np.tile(np.eye(4), (200, 1, 1))
    m[:, :3, :3] = rot.as_matrix()
    np.testing.assert_allclose(q.reshape(-1, 4), dq_from_matrix(m)[:, :4], atol=1e-15)
