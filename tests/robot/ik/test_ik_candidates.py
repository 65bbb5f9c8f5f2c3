"""Choosing among IK candidates grouped by target."""

import numpy as np
import pytest

from gcm_pipeline.robot.ik.candidates import first_smallest


def _by_sort(key, value):
    """Each group's first row after a stable sort by (key, value), written out."""
    order = np.lexsort((value, key))
    return order[np.r_[True, key[order[1:]] != key[order[:-1]]]]


@pytest.mark.parametrize("grouped", [True, False])
@pytest.mark.parametrize("seed", range(6))
def test_first_smallest_is_the_stable_sorts_first(seed, grouped):
    """The nearest candidate per target, ties to the earlier row, as the sort gives,
    whether the candidates come grouped by target (the fast pass) or not."""
    rng = np.random.default_rng(seed)
    key = rng.integers(0, 40, size=500)
    if grouped:
        key = np.sort(key)
    value = rng.integers(0, 6, size=500).astype(float)  # many ties
    if seed % 2:
        value[rng.integers(0, 500, size=20)] = np.nan  # a NaN is never the smallest
    got = first_smallest(key, value)
    np.testing.assert_array_equal(got, _by_sort(key, value))
    np.testing.assert_array_equal(key[got], np.unique(key))


def test_first_smallest_ties_and_empty():
    key = np.array([0, 0, 0, 2, 2, 5])
    value = np.array([3.0, 1.0, 1.0, -0.0, 0.0, 7.0])
    np.testing.assert_array_equal(first_smallest(key, value), [1, 3, 5])
    assert first_smallest(np.zeros(0, dtype=int), np.zeros(0)).size == 0
