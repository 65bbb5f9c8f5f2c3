"""The curvature sums of the deviation bound (``reach/deviation.py``), joint by joint.

``segment_bounds`` sums the curvature bounds joint by joint instead of with
NumPy's ``cumsum``/``sum`` over a row (slow along a short last axis); the sums
must be NumPy's to the bit, or the sample counts (and the paths) could move.
"""

from __future__ import annotations

import numpy as np
import pytest

from gcm_pipeline.reach.deviation import _curvature_sums, lever_arms


def _numpy_sums(dq, lever, order):
    """The former expression: NumPy's cumsum and sum over each row."""
    d = dq[:, order]
    before = np.cumsum(d, axis=1) - d
    return np.sum(lever[order] * d * (d + 2.0 * before), axis=1), dq.sum(axis=1)


@pytest.mark.parametrize("rows", [0, 1, 2, 7, 500])
@pytest.mark.parametrize("order", [np.arange(7), np.array([3, 1, 0, 2, 6, 5, 4])])
def test_curvature_sums_are_numpys_to_the_bit(rows, order):
    """Random changes over sixteen decades, joints in and out of order."""
    rng = np.random.default_rng(rows)
    dq = rng.random((rows, 7)) * 10.0 ** rng.integers(-9, 7, (rows, 7))
    lever = rng.random(7) * 10.0 ** rng.integers(-3, 2, 7)
    got, want = _curvature_sums(dq, lever, order), _numpy_sums(dq, lever, order)
    for g, w in zip(got, want, strict=True):
        assert g.shape == (rows,) and g.tobytes() == w.tobytes()


def test_lever_arms_are_kept_per_robot_and_handed_out_as_copies(panda):
    """The second call reads the robot's cache; changing a result changes no later one."""
    first = lever_arms(panda)
    first[:] = -1.0
    again = lever_arms(panda)
    assert np.all(again > 0) and again.shape == (panda.nq,)
    np.testing.assert_array_equal(again, lever_arms(panda))
