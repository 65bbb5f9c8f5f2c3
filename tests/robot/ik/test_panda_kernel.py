"""The Panda kernel (gcm_pipeline.robot.ik.panda_kernel) against the NumPy closed form.

The same solutions (target, branch, q7 column) in the same order, angles to 1e-6
rad (acos near +-1 amplifies round-off), each reaching its target by Pinocchio
inside the limits.
"""

from __future__ import annotations

import functools

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


def test_nearest_kernel_keeps_the_first_nearest_of_every_solution(compiled, panda, numpy_code):
    """``nearest_to``: per target, the solution the full list's first smallest distance picks.

    Against the kernel's own full list bit for bit (the same closed form, the
    distance summed in NumPy's order); against the NumPy code the same choices up
    to round-off (a tie within 1e-9 may break either way).
    """
    from gcm_pipeline.robot.ik.candidates import first_smallest
    from gcm_pipeline.robot.ik.panda import analytic_solver
    from gcm_pipeline.robot.ik.panda_rounds import joint_levers

    solver = analytic_solver(panda)
    rng = np.random.default_rng(29)
    q = panda.random_configurations(3000, rng)
    rot, pos = panda.chain.pose(q)
    q7 = q[:, 6:7] + np.array([0.0, -0.05, 0.05, 0.4, -1.5, 3.5, 0.0])  # a repeat, too
    pos[:20] += 5.0  # out of reach: no solution
    pref = panda.random_configurations(3000, rng)
    levers = joint_levers(panda)
    args = (rot, pos, q7, panda.lower, panda.upper)
    full = solver.solve(*args)
    dist = np.sum(((full[1] - pref[full[0]]) * levers) ** 2, axis=1)
    first = first_smallest(full[0], dist)
    got = solver.solve(*args, nearest_to=(pref, levers))
    for a, b in zip(got, full, strict=True):
        np.testing.assert_array_equal(a, b[first])
    assert got[0].size > 2900 and np.all(np.diff(got[0]) > 0)
    ref = numpy_code(functools.partial(solver.solve, nearest_to=(pref, levers)), *args)
    np.testing.assert_array_equal(got[0], ref[0])
    d_got = np.sum(((got[1] - pref[got[0]]) * levers) ** 2, axis=1)
    d_ref = np.sum(((ref[1] - pref[ref[0]]) * levers) ** 2, axis=1)
    np.testing.assert_allclose(d_got, d_ref, rtol=0, atol=1e-9)
    same = (got[2] == ref[2]) & (got[3] == ref[3])
    assert same.mean() >= 0.999
    np.testing.assert_allclose(got[1][same], ref[1][same], rtol=0, atol=1e-6)
    for run in (solver.solve, functools.partial(numpy_code, solver.solve)):  # nothing solved
        none = run(rot[:20], pos[:20], q7[:20], panda.lower, panda.upper, None, (pref[:20], levers))
        assert none[0].shape == (0,) and none[1].shape == (0, 7)
