"""Ranking stage: metric columns, order, ties, unreachable rows, errors."""

from __future__ import annotations

import numpy as np
import pytest

from gcm_pipeline.errors import InputError
from gcm_pipeline.ranking.rank import rank
from gcm_pipeline.robot.manipulability import manipulability
from gcm_pipeline.robot.model import Robot
from gcm_pipeline.table import GraspTable


def _table(panda: Robot) -> GraspTable:
    q = panda.random_configurations(8, 1)
    q = np.concatenate([q, q[2:3]])  # row 8 ties with row 2
    reachable = np.ones(9, dtype=bool)
    reachable[5] = False
    q[5] = np.nan
    return GraspTable({"reachable": reachable, "q": q})


@pytest.mark.parametrize(
    "metric,column",
    [
        ("yoshikawa", "manipulability"),
        ("translational", "manip_translation"),
        ("inverse_condition", "inverse_condition"),
        ("joint_limit_margin", "joint_limit_margin"),
    ],
)
def test_rank_order_and_ties(panda: Robot, metric: str, column: str):
    grasps = _table(panda)
    out = rank(grasps, panda, metric=metric, top_k=3)
    values = out[column]
    ranks = out["rank"]
    assert ranks.dtype.kind == "i"
    assert ranks[5] == 0 and np.isnan(values[5])
    ranked = np.flatnonzero(ranks > 0)
    assert sorted(ranks[ranked]) == list(range(1, 9))
    by_rank = ranked[np.argsort(ranks[ranked])]
    assert np.all(np.diff(values[by_rank]) <= 0)
    # equal metric: the lower row index ranks first
    assert values[2] == values[8] and ranks[2] < ranks[8]
    assert out["top"].sum() == 3 and set(ranks[out["top"]]) == {1, 2, 3}
    expected = manipulability(panda, np.nan_to_num(grasps["q"]), metric)
    np.testing.assert_allclose(values[ranked], expected[ranked], rtol=1e-12)
    for col in ("manipulability", "manip_translation", "inverse_condition", "joint_limit_margin"):
        assert out[col].shape == (9,)


def test_rank_errors(panda: Robot):
    grasps = _table(panda)
    with pytest.raises(InputError, match=r"unknown ranking metric 'yoshi'.*joint_limit_margin"):
        rank(grasps, panda, metric="yoshi")
    with pytest.raises(InputError, match="top_k"):
        rank(grasps, panda, top_k=-1)
    with pytest.raises(InputError, match="column 'q'"):
        rank(GraspTable({"reachable": np.ones(2, bool)}), panda)
    with pytest.raises(InputError, match="shape"):
        rank(GraspTable({"reachable": np.ones(2, bool), "q": np.zeros((2, 6))}), panda)


def test_nothing_reachable(panda: Robot):
    grasps = GraspTable({"reachable": np.zeros(3, bool), "q": np.full((3, 7), np.nan)})
    out = rank(grasps, panda)
    assert np.all(out["rank"] == 0) and not out["top"].any()


def test_clearance_and_combined(panda: Robot):
    grasps = _table(panda)
    clearance = np.linspace(0.09, 0.01, 9)
    clearance[8] = clearance[2]  # the tie stays a tie
    clearance[5] = np.nan
    with_clearance = grasps.with_columns(clearance=clearance)
    out = rank(with_clearance, panda, metric="clearance", top_k=3)
    ranked = np.flatnonzero(out["rank"] > 0)
    assert list(ranked[np.argsort(out["rank"][ranked])]) == [0, 1, 2, 8, 3, 4, 6, 7]
    out = rank(with_clearance, panda, metric="combined", weights={"clearance": 1.0})
    np.testing.assert_allclose(
        out["combined"][ranked], (clearance[ranked] - 0.02) / 0.07, atol=1e-12
    )
    assert out["rank"][5] == 0 and np.isnan(out["combined"][5])
    # weights without clearance need no clearance column
    out = rank(grasps, panda, metric="combined", weights={"yoshikawa": 1.0})
    assert np.array_equal(out["rank"], rank(grasps, panda)["rank"])
    for metric in ("clearance", "combined"):
        with pytest.raises(InputError, match=f"metric '{metric}' needs the 'clearance' column"):
            rank(grasps, panda, metric=metric)
