"""The 6R branch kernel (gcm_pipeline.robot.ik.analytic_6r_kernel) against the NumPy code.

The same branches of the same targets in the same order, angles to 1e-12 rad
(each angle's arithmetic is a few IEEE operations rounded once, so they agree
to the bit on the machines measured), on EAIK's real answers and on planted
inputs (least-squares answers, NaN, repeats within the branch tolerance and
just outside it, angles at the limits and at +-pi).
"""

from __future__ import annotations

import numpy as np
import pytest

from gcm_pipeline.config.robot_spec import load_robot
from gcm_pipeline.robot.ik.analytic_6r import _SAME_BRANCH, six_r_solver

#: Each test starts with the kernels on, whatever the environment says.
pytestmark = pytest.mark.usefixtures("kernels_on")


@pytest.fixture(scope="module")
def ur5():
    return load_robot("ur5")


def _same(got, ref) -> None:
    np.testing.assert_array_equal(got[0], ref[0])
    assert got[1].shape == ref[1].shape
    np.testing.assert_allclose(got[1], ref[1], rtol=0, atol=1e-12)


@pytest.mark.parametrize("limits", ["spec", "half_turn", "narrow"])
def test_branches_equal_numpy_on_eaik_answers(ur5, numpy_code, pose_errors, limits) -> None:
    solver = six_r_solver(ur5)
    assert solver is not None
    rng = np.random.default_rng(5)
    q = ur5.random_configurations(3000, rng)
    q[:300, 4] = 0.0  # wrist singular: EAIK may repeat a branch or answer in least squares
    rot, pos = ur5.chain.pose(q)
    pos[300:600] += 5.0  # beyond reach: least squares or nothing
    lower, upper = {
        "spec": (ur5.lower, ur5.upper),
        "half_turn": (np.full(6, -np.pi), np.full(6, np.pi)),
        "narrow": (0.3 * ur5.lower, 0.5 * ur5.upper),
    }[limits]
    reference = ur5.random_configurations(3000, rng)
    args = (rot, pos, lower, upper, reference)
    got = solver.solve(*args)
    ref = numpy_code(solver.solve, *args)
    _same(got, ref)
    assert got[0].size > 1000 and not np.isin(np.arange(300, 600), got[0]).any()
    pe, re = pose_errors(ur5, got[1], rot[got[0]], pos[got[0]])
    assert pe.max() < 1e-9 and re.max() < 1e-9
    assert np.all((got[1] >= lower) & (got[1] <= upper))


def test_planted_answers_equal_numpy(ur5, compiled, numpy_code) -> None:
    """Repeats, least-squares and NaN answers, angles at +-pi and at the limits."""
    solver = six_r_solver(ur5)
    rng = np.random.default_rng(11)
    n = 400
    counts = rng.integers(0, 9, n)
    m = int(counts.sum())
    values = np.array([np.pi, -np.pi, 0.0, -0.0, 2.0 * np.pi, -3.0 * np.pi, 6.18318531, 1e-17])
    q = np.where(rng.random((m, 6)) < 0.2, rng.choice(values, (m, 6)), rng.uniform(-7, 7, (m, 6)))
    idx = np.repeat(np.arange(n), counts)
    for i in rng.integers(0, m, m // 2):  # copies of another answer of the target
        j = int(rng.choice(np.flatnonzero(idx == idx[i])))
        hair = rng.choice([0.0, 0.5, 0.99, 1.01, 3.0], 6) * _SAME_BRANCH
        q[j] = q[i] + hair * rng.choice([-1, 1], 6) + 2.0 * np.pi * rng.integers(-1, 2, 6)
    q[rng.random((m, 6)) < 0.01] = np.nan
    exact = rng.random(m) > 0.1
    reference = ur5.random_configurations(n, rng)
    lower, upper = ur5.lower, ur5.upper

    def numpy_branches():
        # the NumPy code's steps after EAIK (SixRAnalyticIK.raw and .solve)
        from gcm_pipeline.robot.ik.analytic_6r import nearest_copy, repeated_branches

        keep = exact & np.all(np.isfinite(q), axis=1)
        at, wq = idx[keep], np.remainder(q[keep] + np.pi, 2.0 * np.pi) - np.pi
        first = ~repeated_branches(at, wq)
        at, wq = at[first], nearest_copy(wq[first], reference[at[first]], lower, upper)
        inside = np.all(np.isfinite(wq), axis=1)
        return at[inside], wq[inside]

    got = compiled.six_r_branches(q, counts, exact, reference, lower, upper, _SAME_BRANCH)
    ref = numpy_code(numpy_branches)
    _same(got, ref)
    assert 0 < got[0].size < m  # some dropped, some kept
    # a target without answers, and none at all
    empty = compiled.six_r_branches(
        np.zeros((0, 6)), np.zeros(3, dtype=np.intp), np.zeros(0, bool), reference[:3],
        lower, upper, _SAME_BRANCH,
    )  # fmt: skip
    assert empty[0].shape == (0,) and empty[1].shape == (0, 6)
    assert solver is not None
