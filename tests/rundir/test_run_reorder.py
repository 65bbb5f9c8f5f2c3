"""read_run puts the candidates first: in place where it can, the same table as a copy."""

from __future__ import annotations

import numpy as np
import pytest

from gcm_pipeline.errors import InputError
from gcm_pipeline.rundir import run as run_files
from gcm_pipeline.table import GraspTable


def _columns(n: int, rng: np.random.Generator) -> dict[str, np.ndarray]:
    """Columns of every kind a run's table has, some owned, some not."""
    shared = rng.random((n, 4))
    frozen = np.frombuffer(rng.random(n).tobytes(), dtype=np.float64)  # read-only memory
    return {
        "dq": rng.random((n, 8)),
        "rank": rng.integers(0, 9, n),
        "reason": rng.choice(np.array(["", "no_ik", "approach, blocked"]), n),
        "reachable": rng.random(n) > 0.5,
        "weights": np.where(rng.random((n, 3)) > 0.8, np.nan, rng.random((n, 3))),
        "left": shared[:, :2],  # two columns of one array: never moved in place
        "right": shared[:, 2:],
        "frozen": frozen,
        "strided": rng.random((n, 2))[:, 0],
        "objects": np.array([f"row {i}" for i in range(n)] + [None], dtype=object)[:n].copy(),
    }


def _expected(cols: dict[str, np.ndarray], rows: np.ndarray) -> dict[str, np.ndarray]:
    rest = np.setdiff1d(np.arange(len(cols["dq"])), rows)
    perm = np.concatenate([rows, rest]).astype(np.int64)
    return {k: v[perm].copy() for k, v in cols.items()}


@pytest.mark.parametrize(
    "n, rows",
    [
        (0, []),
        (1, []),
        (1, [0]),
        (5, [0, 1]),  # already first
        (5, [4]),
        (5, [4, 0]),
        (7, [6, 5, 4, 3, 2, 1, 0]),  # every row
        (50, [49, 3, 17, 0, 18, 48]),  # neighbours and both ends, not sorted
        (200, list(range(199, -1, -3))),
    ],
)
def test_candidates_first_is_the_take_of_candidates_then_the_rest(n, rows):
    rng = np.random.default_rng(n + len(rows))
    cols = _columns(n, rng)
    rows = np.asarray(rows, dtype=np.int64)
    want = _expected(cols, rows)
    is_row = np.zeros(n, dtype=bool)
    is_row[rows] = True
    got = run_files._candidates_first(GraspTable(cols), rows, is_row)
    assert list(got) == list(want)
    for name, values in want.items():
        assert got[name].dtype == values.dtype and got[name].shape == values.shape, name
        assert got[name].tobytes() == values.tobytes(), name


def test_many_candidates_are_reordered_by_a_copy(monkeypatch):
    monkeypatch.setattr(run_files, "_MOVES_IN_PLACE", 2)
    rng = np.random.default_rng(3)
    cols = _columns(30, rng)
    rows = np.array([29, 4, 11], dtype=np.int64)
    want = _expected(cols, rows)
    is_row = np.zeros(30, dtype=bool)
    is_row[rows] = True
    got = run_files._candidates_first(GraspTable(cols), rows, is_row)
    for name, values in want.items():
        assert got[name].tobytes() == values.tobytes(), name


def test_a_row_named_by_v1_v3_that_is_not_a_candidate_is_refused(tmp_path, monkeypatch):
    n = 6
    cols = {
        "dq": np.tile([1.0, 0, 0, 0, 0, 0, 0, 0], (n, 1)),
        "vertices": np.array([[-1, -1, -1]] * 3 + [[0, 1, 2], [0, 4, 2], [5, 1, 2]]),
    }
    monkeypatch.setattr(run_files, "read_summary", lambda path: {})
    monkeypatch.setattr(run_files, "read_grasps_csv", lambda path: GraspTable(cols))
    monkeypatch.setattr(run_files, "read_manifold", lambda path, n_rows: _Mesh())
    monkeypatch.setattr(run_files, "manifold_vertex_rows", lambda path, n: np.array([2, 0, 1]))
    for name in ("grasps.csv", "summary.json", "manifold.npz"):
        (tmp_path / name).write_text("")
    with pytest.raises(InputError, match=r"grasps.csv: v1..v3 name row 4, which is not a cand"):
        run_files.read_run(tmp_path)


class _Mesh:
    chart = np.zeros((3, 2))
