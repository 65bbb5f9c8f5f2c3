"""The nearest reachable rows of a few queries: one pass over the rows, the KD-tree's answer."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from gcm_pipeline.geometry.dualquat import dq_from_pos_quat
from gcm_pipeline.geometry.pose_metric import other_sign_features, pose_features
from gcm_pipeline.manifold import query as Q


def _features(n: int, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    quat = Rotation.random(n, random_state=seed).as_quat(scalar_first=True)
    return pose_features(dq_from_pos_quat(rng.uniform(-0.3, 0.3, (n, 3)), quat), 0.1)


def _tree_answer(feat: np.ndarray, queries: np.ndarray, k: int):
    tree = cKDTree(np.concatenate((feat, other_sign_features(feat))))
    dist, idx = tree.query(queries, k=k)
    return np.reshape(dist, (len(queries), k)), np.reshape(idx, (len(queries), k))


def _check(feat: np.ndarray, queries: np.ndarray, k: int) -> None:
    got = Q.nearest_of_both_signs(feat, queries, k)
    want = _tree_answer(feat, queries, k)
    assert got[0].tobytes() == want[0].tobytes()  # the tree's distances, bit for bit
    assert np.array_equal(got[1], want[1])


@pytest.mark.parametrize("n, k", [(1, 2), (2, 4), (3, 2), (50, 8), (2000, 8)])
def test_few_queries_get_the_trees_rows_and_distances(n, k):
    feat = _features(n, n)
    rng = np.random.default_rng(7)
    near = feat[rng.integers(0, n, 4)] + rng.normal(0, 0.01, (4, 7))
    flipped = other_sign_features(feat[rng.integers(0, n, 2)])  # nearest through the other sign
    _check(feat, np.concatenate((near, flipped, rng.normal(0, 1, (2, 7)))), k)


def test_a_query_at_a_row_and_far_from_all():
    feat = _features(300, 1)
    _check(feat, np.concatenate((feat[:3], feat[:1] + 50.0)), 8)


def test_ties_get_the_trees_order():
    feat = _features(40, 2)
    feat = np.concatenate((feat, feat[:10], feat[:10]))  # rows at one pose: equal distances
    _check(feat, feat[[0, 5, 9, 20]], 8)
    _check(feat, feat[[0, 5, 9, 20]] + 1e-3, 6)


def test_many_queries_use_one_tree():
    feat = _features(500, 3)
    queries = feat[: Q._BRUTE_QUERIES + 1] + 1e-3
    _check(feat, queries, 8)
