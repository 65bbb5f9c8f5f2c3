"""``nearest_to`` with distances that are not finite: the kernel keeps what NumPy keeps.

The NumPy code sorts the distances (NaN last, the first of ties); the kernel
must keep a solution for every target that has one, as it does, even where the
distance to ``pref`` is NaN or infinite (a NaN in ``pref`` or ``levers``).
"""

from __future__ import annotations

import functools

import numpy as np
import pytest

#: Each test starts with the kernels on, whatever the environment says.
pytestmark = pytest.mark.usefixtures("kernels_on")


def test_nearest_kernel_keeps_a_solution_where_the_distance_is_not_finite(
    compiled, panda, numpy_code
):
    from gcm_pipeline.robot.ik.panda import analytic_solver
    from gcm_pipeline.robot.ik.panda_rounds import joint_levers

    solver = analytic_solver(panda)
    rng = np.random.default_rng(31)
    q = panda.random_configurations(600, rng)
    rot, pos = panda.chain.pose(q)
    q7 = q[:, 6:7] + np.array([0.0, -0.3, 0.3, 1.0])
    pref = panda.random_configurations(600, rng)
    pref[::3, 2] = np.nan  # every solution of these targets at NaN
    pref[1::3, 4] = np.inf  # at inf or NaN
    args = (rot, pos, q7, panda.lower, panda.upper)
    for levers in (joint_levers(panda), np.r_[np.nan, np.ones(6)]):
        want = numpy_code(functools.partial(solver.solve, nearest_to=(pref, levers)), *args)
        got = solver.solve(*args, nearest_to=(pref, levers))
        full = solver.solve(*args)
        assert np.array_equal(got[0], np.unique(full[0]))  # every target with a solution
        np.testing.assert_array_equal(got[0], want[0])
        # where every distance is NaN (or inf): the first solution, as NumPy's stable sort
        first = np.flatnonzero(np.r_[True, full[0][1:] != full[0][:-1]])
        bad = np.isin(got[0], np.flatnonzero(~np.isfinite(pref).all(axis=1)))
        if not np.isfinite(levers).all():
            bad[:] = True
        np.testing.assert_array_equal(got[1][bad], full[1][first][bad])
