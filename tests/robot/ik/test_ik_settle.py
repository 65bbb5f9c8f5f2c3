"""solve_ik's ``settle`` callback: each candidate once, in order; the settled searched no more."""

import numpy as np
import pytest

from gcm_pipeline.errors import InputError
from gcm_pipeline.robot.ik import pool, solve_ik

OPTS = {"min_solutions": 6, "first_round_seeds": 3, "round_seeds": 3, "random_seed": 0}


def _targets(robot, n, seed=3):
    rng = np.random.default_rng(seed)
    return robot.fk_pinocchio(rng.uniform(robot.lower, robot.upper, size=(n, robot.nq)))


class _Recorder:
    """A settle callback: records what it is given; settles the listed targets at once."""

    def __init__(self, n, settle_at_first):
        self.index, self.q = [], []
        self.first_calls = {}
        self.calls = 0
        self.settled = np.zeros(n, dtype=bool)
        self.settle_at_first = set(settle_at_first)

    def __call__(self, index, q):
        assert index.ndim == 1 and q.shape == (index.size, 7)
        self.calls += 1
        self.index.append(index.copy())
        self.q.append(q.copy())
        for t in np.unique(index):
            self.first_calls.setdefault(int(t), self.calls)
            if int(t) in self.settle_at_first:
                self.settled[t] = True
        return self.settled.copy()

    def given(self):
        """What it was given, stably sorted by target (the order of ``result.candidates``)."""
        index, q = np.concatenate(self.index), np.concatenate(self.q)
        order = np.argsort(index, kind="stable")
        return index[order], q[order]


@pytest.mark.parametrize("analytic", [True, False])
def test_settle_sees_every_candidate_once_and_stops_the_settled(panda, analytic):
    n = 16 if analytic else 8
    targets = _targets(panda, n)
    kw = {**OPTS, "analytic": analytic}
    full = solve_ik(panda, targets, return_all=True, **kw).candidates
    rec = _Recorder(n, settle_at_first=range(0, n, 2))  # the even targets
    res = solve_ik(panda, targets, return_all=True, settle=rec, **kw)
    cand = res.candidates
    index, q = rec.given()
    np.testing.assert_array_equal(index, cand.index)  # every candidate once, in order
    np.testing.assert_array_equal(q, cand.q)
    assert rec.calls > 1  # between the stages, not only at the end
    stopped = 0
    for t in range(n):
        mine, theirs = cand.q[cand.index == t], full.q[full.index == t]
        if t % 2:  # not settled: the same search
            np.testing.assert_array_equal(mine, theirs)
        else:  # settled when first given candidates: those only, the start of the full list
            first = rec.first_calls.get(t)
            if first is None:
                assert mine.size == 0 and theirs.size == 0
                continue
            np.testing.assert_array_equal(mine, rec.q[first - 1][rec.index[first - 1] == t])
            np.testing.assert_array_equal(mine, theirs[: len(mine)])
            stopped += len(theirs) - len(mine)
    assert stopped > 0  # the settled targets were searched less


def test_settle_indices_across_chunks_and_far_targets(panda, monkeypatch):
    """Chunks of the backend and targets dropped as out of reach keep settle's indices."""
    targets = _targets(panda, 12, seed=5)
    targets[4, :3, 3] = [5.0, 0.0, 0.0]  # far out of reach: never given to the backend
    full = solve_ik(panda, targets, return_all=True, **OPTS).candidates
    monkeypatch.setattr(pool, "_CHUNK", 5)
    rec = _Recorder(12, settle_at_first=())
    res = solve_ik(panda, targets, return_all=True, settle=rec, workers=2, **OPTS)
    index, q = rec.given()
    np.testing.assert_array_equal(index, full.index)
    np.testing.assert_array_equal(q, full.q)
    np.testing.assert_array_equal(res.candidates.q, full.q)
    assert 4 not in index and res.reason[4] == "out_of_reach"


def test_settle_needs_pinocchio_and_return_all(panda):
    targets = _targets(panda, 2)
    with pytest.raises(InputError, match="settle"):
        solve_ik(panda, targets, settle=lambda i, q: np.zeros(2, bool))
    with pytest.raises(InputError, match="settle"):
        solve_ik(panda, targets, "mink", return_all=True, settle=lambda i, q: np.zeros(2, bool))


@pytest.mark.parametrize(
    "answer",
    [True, None, "n - 1", "n + 1", "(n, 1)", "empty"],
)
def test_a_settle_answer_of_the_wrong_shape_is_one_line(panda, answer):
    # it used to surface as an IndexError or a broadcast ValueError from inside the
    # stages (or, one entry too long, pass unnoticed)
    n = 8
    targets = _targets(panda, n)
    shapes = {"n - 1": (n - 1,), "n + 1": (n + 1,), "(n, 1)": (n, 1), "empty": (0,)}

    def settle(index, q):
        return np.zeros(shapes[answer], dtype=bool) if answer in shapes else answer

    with pytest.raises(InputError, match=rf"settle returned shape .*, expected \({n},\)"):
        solve_ik(panda, targets, "pinocchio", return_all=True, settle=settle, **OPTS)
