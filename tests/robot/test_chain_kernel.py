"""The chain kernels (gcm_pipeline.robot.chain_kernel) against their NumPy references.

Forward kinematics and Jacobians (``KinematicChain._forward``) on every chain
shape (a whole arm, one with a tool, a sub-chain whose joints are not the first
columns of q) and row count; the deviation samples along joint segments
(``reach.deviation.segment_bounds``). Closed forms: values to tolerances far
above round-off, and against Pinocchio; never the last bits.
"""

from __future__ import annotations

import numpy as np
import pinocchio as pin
import pytest

from gcm_pipeline.config.robot_spec import load_robot
from gcm_pipeline.robot.chain import KinematicChain

#: Each test starts with the kernels on, whatever the environment says.
pytestmark = pytest.mark.usefixtures("kernels_on")


def _pin_frames(model, frame_id, q):
    """Pose (rotations (N, 3, 3), positions (N, 3)) and world-aligned Jacobians of a
    frame, by Pinocchio itself, one configuration at a time."""
    data = model.createData()
    rot, pos, jac = [], [], []
    for qi in np.atleast_2d(q):
        pin.computeJointJacobians(model, data, qi)
        pin.updateFramePlacements(model, data)
        placement = data.oMf[frame_id]
        rot.append(placement.rotation.copy())
        pos.append(placement.translation.copy())
        jac.append(
            pin.getFrameJacobian(model, data, frame_id, pin.ReferenceFrame.LOCAL_WORLD_ALIGNED)
        )
    return np.array(rot), np.array(pos), np.array(jac)


# --- forward kinematics -----------------------------------------------------------------


def _chains(panda):
    """Chains by name: (chain, the model, the frame's id in it)."""
    ur5 = load_robot("ur5")
    link4 = panda.model.getFrameId("panda_link4")
    return {
        "panda": (panda.chain, panda.model, panda.grasp_frame_id),
        "ur5_tool": (ur5.chain, ur5.model, ur5.grasp_frame_id),
        # joints 1-4 of 7: q_index is not 0..nq-1, the Jacobian's last columns are zero
        "panda_link4": (KinematicChain(panda.model, link4), panda.model, link4),
    }


@pytest.mark.parametrize("name", ["panda", "ur5_tool", "panda_link4"])
@pytest.mark.parametrize("n", [0, 1, 1000])
def test_fk_kernel_equals_numpy(compiled, panda, name, n, numpy_code):
    """Forward kinematics is a closed form: no iteration amplifies round-off.

    The kernel and the NumPy code sum in other orders on other CPUs; each
    result is within a few ulps of the exact one, so they agree, and agree
    with Pinocchio, to 1e-12 (about 5,000 ulps of values of order 1).
    """
    chain, model, frame_id = _chains(panda)[name]
    rng = np.random.default_rng(n)
    q = rng.uniform(-np.pi, np.pi, (n, chain.nq))
    q.setflags(write=False)  # read-only arrays are taken too (a robot's home is one)
    ref = numpy_code(chain._forward, q, True)
    out = chain._forward(q, True)
    for got, want in zip(out, ref, strict=True):
        assert got.shape == want.shape
        np.testing.assert_allclose(got, want, rtol=0, atol=1e-12)
    if name == "panda_link4":
        assert list(chain.q_index) == [0, 1, 2, 3] and chain.nq == 7
        assert not out[2][:, :, 4:].any()
    rot, pos, jac = chain._forward(q, False)
    assert jac is None
    np.testing.assert_allclose(rot, ref[0], rtol=0, atol=1e-12)
    np.testing.assert_allclose(pos, ref[1], rtol=0, atol=1e-12)
    # the public API, in chunks (a strided q is accepted too)
    big = np.repeat(q, 3, axis=0)[::3] if n else q
    np.testing.assert_allclose(chain.pose_jacobian(big)[2], ref[2], rtol=0, atol=1e-12)
    # and what Pinocchio computes (the first 50 rows: a Python loop)
    if n:
        want = _pin_frames(model, frame_id, q[:50])
        for got, exact in zip(out, want, strict=True):
            np.testing.assert_allclose(got[:50], exact, rtol=0, atol=1e-12)


@pytest.mark.parametrize("reject", [np.inf, 2e-3])
def test_segment_bound_kernel_equals_numpy(compiled, panda, reject, numpy_code):
    from gcm_pipeline.reach.deviation import lever_arms, sample_deviation, segment_bounds

    rng = np.random.default_rng(12)
    n = 2000
    q_a = panda.random_configurations(n, rng)
    # short and long joint segments: 2 to 64 samples
    q_b = q_a + rng.choice([0.005, 0.05, 0.3], size=(n, 1)) * rng.normal(size=q_a.shape)
    rot, pos = panda.chain.pose(q_a)
    offsets = rng.normal(0.0, 0.05, (n, 3))
    offsets[:10] = 0.0  # a move of zero length
    args = (panda, lever_arms(panda), q_a, q_b, pos, rot, offsets, 0.12, 1e-3, reject)
    got = segment_bounds(*args)
    ref = numpy_code(segment_bounds, *args)
    # sums of a few samples' distances: round-off only (1e-9 is 10^7 ulps); except a
    # segment whose midpoint lies within round-off of ``reject`` (its bound is either
    # the midpoint's or the full one): none of the 2,000 here, on any CPU
    mid = numpy_code(sample_deviation, panda, 0.5 * (q_a + q_b), pos, rot, offsets, 0.12)
    sure = np.abs(mid - reject) > 1e-9
    assert sure.all()
    np.testing.assert_allclose(got, ref, rtol=1e-9, atol=1e-12)
    assert np.unique(got > 5e-3).size == 2
    # what matters: a segment whose midpoint exceeds ``reject`` is rejected; any other
    # gets a bound, above the deviation sampled 8x finer than any row's samples
    assert np.all(got[mid > reject] > reject)
    s = np.linspace(0.0, 1.0, 513)
    rows = np.arange(0, n, 10)
    qs = q_a[rows, None] + s[None, :, None] * (q_b - q_a)[rows, None]
    fine = sample_deviation(
        panda,
        qs.reshape(-1, panda.nq),
        np.repeat(pos[rows], s.size, axis=0),
        np.repeat(rot[rows], s.size, axis=0),
        np.repeat(offsets[rows], s.size, axis=0),
        0.12,
    ).reshape(rows.size, s.size)
    kept = mid[rows] <= reject
    assert kept.sum() >= 10
    assert np.all(got[rows][kept] >= fine.max(axis=1)[kept] - 1e-12)
    # arrays in any memory layout (the kernel takes C arrays)
    strided = (*args[:2], np.asfortranarray(q_a), q_b[:, ::-1][:, ::-1], *args[4:])
    np.testing.assert_array_equal(segment_bounds(*strided), got)


@pytest.mark.parametrize("max_step", [0.05, 0.5, 5.0])
def test_grid_path_kernel_equals_numpy(compiled, max_step):
    """A move's grid points through its waypoints: the kernel does the NumPy code's
    operations (differences, products, sums, each rounded once) in its order, so the
    paths are equal to the bit on any CPU, and so is each path's first jump."""
    from gcm_pipeline.reach.path import _grid_points

    rng = np.random.default_rng(5)
    m, sub, steps, nq = 500, 8, 10, 7
    width = sub * steps + 1
    have = rng.random((m, width)) < rng.choice([0.02, 0.15, 1.0], size=(m, 1))
    have[:, 0] = have[:, -1] = True  # every path has waypoints at its ends
    slot = np.full((m, width), -1, dtype=np.int32)  # the engine's slots are int32
    slot[have] = rng.permutation(have.sum())
    knots = rng.normal(0.0, 0.3, (have.sum(), nq))
    knots[slot[7, 0], 3] = np.nan  # a NaN joint: no jump found where it enters
    path, jump_at = compiled.grid_path(slot, knots, sub, max_step)
    ref_path, ref_jump = _grid_points(slot, knots, sub, max_step)
    np.testing.assert_array_equal(path, ref_path)
    np.testing.assert_array_equal(jump_at, ref_jump)
    # what it means: a waypoint on a grid point is that point; the first jump over
    # max_step is where the largest joint change first exceeds it
    r, at = np.nonzero(have[:, ::sub])
    np.testing.assert_array_equal(path[r, at], knots[slot[r, at * sub]])
    change = np.abs(np.diff(path, axis=1)).max(axis=2)
    over = change > max_step
    want = np.where(over.any(axis=1), over.argmax(axis=1), -1)
    np.testing.assert_array_equal(jump_at, want)
    assert 0 < (jump_at >= 0).sum() < m or max_step == 5.0


# --- cosines and sines of the joint frames ----------------------------------------------


def test_cos_sin_kernel_equals_numpy_cos_sin(compiled):
    """``cos_sin`` (one range reduction and fdlibm's polynomials, vectorised) against
    NumPy's ``cos`` and ``sin`` (libm): within two ulps of each value, or 1e-20 absolute
    near a zero; libm's own values beyond the reduced range, inf and nan included."""
    rng = np.random.default_rng(3)
    k = np.arange(-3000, 3001)[:, None]
    cases = {
        "joint angles": rng.uniform(-2 * np.pi, 2 * np.pi, (5000, 7)),
        "wide": rng.uniform(-1e5, 1e5, (4000, 5)),
        # at and around every quadrant's boundary: the reduction's cancellation and the
        # quadrant's selection (k/4 rounds half to even)
        "near k pi/2": k * (np.pi / 2) + np.array([0.0, 1e-15, -1e-12, 1e-8, -0.785, 0.785]),
        "tiny": np.array([[0.0, -0.0, 1e-300, 5e-324, -1e-8, 1e-20]]),
        "libm's": np.array([[1e5 + 1, -3e10, 1e300, -np.inf, np.inf, np.nan]]),
        "one": np.array([[0.3]]),
        "none": np.zeros((0, 7)),
    }
    for name, q in cases.items():
        cos, sin = compiled.cos_sin(q)
        assert cos.shape == sin.shape == q.shape, name
        with np.errstate(invalid="ignore"):
            for got, ref in ((cos, np.cos(q)), (sin, np.sin(q))):
                np.testing.assert_array_equal(np.isnan(got), np.isnan(ref), err_msg=name)
                ok = np.isfinite(ref)
                err = np.abs(got[ok] - ref[ok])
                assert np.all(err <= np.maximum(2 * np.spacing(np.abs(ref[ok])), 1e-20)), name
    # a strided, read-only input: the same values as its C-contiguous copy
    q = cases["joint angles"]
    view = np.asfortranarray(q)[:, ::2]
    view.flags.writeable = False
    for got, ref in zip(compiled.cos_sin(view), compiled.cos_sin(q[:, ::2].copy()), strict=True):
        np.testing.assert_array_equal(got, ref)


def test_cos_sin_keeps_the_sign_of_a_zero_sine(compiled):
    """``sin(-0.0)`` is ``-0.0`` (libm's, NumPy's); the polynomial ``r + r z p(z)`` alone
    gives ``+0.0`` (``-0.0 + 0.0``)."""
    q = np.array([[-0.0, 0.0, -5e-324, 5e-324]])
    cos, sin = compiled.cos_sin(q)
    np.testing.assert_array_equal(np.signbit(sin), np.signbit(np.sin(q)))
    np.testing.assert_array_equal(cos, np.cos(q))
