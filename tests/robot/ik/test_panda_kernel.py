"""The Panda kernel (gcm_pipeline.robot.ik.panda_kernel) against the NumPy closed form.

The same solutions (target, branch, q7 column) in the same order, angles to 1e-6
rad (acos near +-1 amplifies round-off), each reaching its target by Pinocchio
inside the limits.
"""

from __future__ import annotations

import numpy as np
import pytest

#: Each test starts with the kernels on, whatever the environment says.
pytestmark = pytest.mark.usefixtures("kernels_on")


@pytest.mark.parametrize("near", [False, True])
def test_closed_form_kernel_equals_numpy(
    monkeypatch, compiled, panda, near, numpy_code, pose_errors
):
    from gcm_pipeline.robot.ik.panda import analytic_solver

    solver = analytic_solver(panda)
    rng = np.random.default_rng(13)
    q = panda.random_configurations(2000, rng)
    rot, pos = panda.chain.pose(q)
    q7 = q[:, 6:7] + np.array([0.0, -0.05, 0.05, 0.4, -1.5, 3.5])  # some outside the limits
    pos[:20] += 5.0  # out of reach: no solution
    args = (rot, pos, q7, panda.lower, panda.upper, (q, 0.3) if near else None)
    got = solver.solve(*args)
    ref = numpy_code(solver.solve, *args)
    # the same solutions, as (target, branch, q7 column); a solution within round-off
    # of a joint limit (or of acos's domain) may be kept by one and not the other:
    # at most 0.1 % (none on the machines measured)
    keys = [set(zip(a[0].tolist(), a[2].tolist(), a[3].tolist(), strict=True)) for a in (got, ref)]
    assert len(keys[0] ^ keys[1]) <= 1e-3 * len(keys[1])
    assert len(got[0]) > 2000 and not np.isin(np.arange(20), got[0]).any()
    # in the same order, the same angles: a closed form, where only acos near +-1
    # amplifies round-off (an input off by 1 ulp moves the angle by up to
    # sqrt(2 eps) = 2e-8 rad; 1e-6 rad leaves 50x)
    common = keys[0] & keys[1]
    at = [np.array([k in common for k in zip(a[0], a[2], a[3], strict=True)]) for a in (got, ref)]
    fields = zip(("index", "branch", "column"), got[::2] + got[3:], ref[::2] + ref[3:], strict=True)
    for name, a, b in fields:
        np.testing.assert_array_equal(a[at[0]], b[at[1]], err_msg=name)
    np.testing.assert_allclose(got[1][at[0]], ref[1][at[1]], rtol=0, atol=1e-6)
    # every solution reaches its target, as Pinocchio computes it, within the limits
    pe, re = pose_errors(panda, got[1], rot[got[0]], pos[got[0]])
    assert pe.max() < 1e-9 and re.max() < 1e-9
    assert np.all((got[1] >= panda.lower) & (got[1] <= panda.upper))
    if near:
        assert np.all(np.abs(got[1] - q[got[0]]) <= 0.3)
    assert solver.solve(rot[:0], pos[:0], q7[:0], panda.lower, panda.upper)[1].shape == (0, 7)


@pytest.mark.parametrize("group", [1, 3, 9])
def test_nearest_per_group_leaves_out_only_farther_solutions(compiled, panda, group):
    """With ``nearest``, the kernel's solutions are a subset of all of them, in the same
    order, and hold the nearest of each (target, group of columns) and its ties."""
    from gcm_pipeline.robot.ik.candidates import first_smallest
    from gcm_pipeline.robot.ik.panda import analytic_solver

    solver = analytic_solver(panda)
    rng = np.random.default_rng(29)
    q = panda.random_configurations(600, rng)
    rot, pos = panda.chain.pose(q)
    offsets = np.array([0.0, -0.05, 0.05, -0.1, 0.1, -0.2, 0.2, -0.4, 0.4])
    q7 = np.clip(q[:, 6:7] + offsets, panda.lower[6], panda.upper[6])  # 9 columns
    n_groups = -(-9 // group)
    ref = panda.random_configurations(600 * n_groups, rng).reshape(600, n_groups, 7)
    ref[:5] = np.nan  # no reference: nothing left out
    ref[5:10, :, :] = q[5:10, None, :]  # the target's own configuration: distance 0
    full = solver.solve(rot, pos, q7, panda.lower, panda.upper)
    got = solver.solve(rot, pos, q7, panda.lower, panda.upper, nearest=(ref, group))
    key = [np.column_stack([a[0], a[3], a[2]]) for a in (full, got)]
    rows = {tuple(r): i for i, r in enumerate(key[0].tolist())}
    where = np.array([rows[tuple(r)] for r in key[1].tolist()])
    assert np.all(np.diff(where) > 0)  # a subset, in order
    np.testing.assert_array_equal(got[1], full[1][where])  # the same angles, bit for bit
    assert len(got[0]) < 0.8 * len(full[0])  # the farther branches were left out
    assert set(got[0][np.isin(got[0], np.arange(5))]) == set(full[0][full[0] < 5])

    def nearest(at, cq, col):
        grp = at * n_groups + col // group
        dist = np.sum((cq - ref[at, col // group]) ** 2, axis=1)
        pick = first_smallest(grp, np.where(np.isfinite(dist), dist, np.inf))
        return grp[pick], cq[pick]

    want, have = nearest(full[0], full[1], full[3]), nearest(got[0], got[1], got[3])
    for a, b in zip(want, have, strict=True):
        np.testing.assert_array_equal(a, b)
