"""Ranking by the synthesiser's score: the ``score`` metric and its ``combined`` weight."""

from __future__ import annotations

import numpy as np
import pytest

from gcm_pipeline.errors import InputError
from gcm_pipeline.ranking.rank import rank
from gcm_pipeline.robot.model import Robot
from gcm_pipeline.table import GraspTable


def _table(panda: Robot, score: list[float]) -> GraspTable:
    n = len(score)
    q = panda.random_configurations(n, 1)
    reachable = np.ones(n, dtype=bool)
    reachable[1] = False  # the best score, but unreachable: not ranked
    q[1] = np.nan
    return GraspTable({"reachable": reachable, "q": q, "score": np.array(score)})


def test_rank_by_score(panda: Robot):
    grasps = _table(panda, [0.3, 0.99, 0.8, 0.5, 0.8])
    out = rank(grasps, panda, metric="score", top_k=2)
    # descending score among reachable rows; the tie (rows 2, 4) by row
    assert out["rank"].tolist() == [4, 0, 1, 3, 2]
    assert out["top"].tolist() == [False, False, True, False, True]


def test_score_weight_in_combined(panda: Robot):
    grasps = _table(panda, [0.3, 0.99, 0.8, 0.5, 0.1])
    only = rank(grasps, panda, metric="combined", weights={"score": 1.0})
    reach = np.asarray(grasps["reachable"])
    s = grasps["score"][reach]
    np.testing.assert_allclose(only["combined"][reach], (s - s.min()) / (s.max() - s.min()))
    assert np.isnan(only["combined"][1])
    both = rank(grasps, panda, metric="combined", weights={"score": 1.0, "yoshikawa": 1.0})
    m = both["manipulability"][reach]
    want = 0.5 * (s - s.min()) / (s.max() - s.min()) + 0.5 * (m - m.min()) / (m.max() - m.min())
    np.testing.assert_allclose(both["combined"][reach], want)


def test_score_metric_needs_the_column(panda: Robot):
    grasps = _table(panda, [0.3, 0.99, 0.8])
    no_score = GraspTable({k: grasps[k] for k in ("reachable", "q")})
    with pytest.raises(InputError, match="ranking metric 'score' needs the 'score' column"):
        rank(no_score, panda, metric="score")
    with pytest.raises(InputError, match="ranking metric 'combined' needs the 'score' column"):
        rank(no_score, panda, metric="combined", weights={"score": 1.0})
