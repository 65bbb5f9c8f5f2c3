from __future__ import annotations

import numpy as np
import pytest

from gcm_pipeline import GraspTable, InputError


def test_columns_share_arrays_and_are_read_only() -> None:
    dq = np.zeros((5, 8))
    t = GraspTable({"dq": dq})
    t2 = t.with_columns(reachable=np.ones(5, bool))
    assert len(t) == len(t2) == 5
    assert t2["dq"] is t["dq"]
    assert t2.columns == ("dq", "reachable")
    with pytest.raises(ValueError):
        t["dq"][0, 0] = 1.0


def test_length_mismatch_is_an_error() -> None:
    with pytest.raises(InputError, match="'b' has 3 rows, expected 2"):
        GraspTable({"a": np.zeros(2), "b": np.zeros(3)})
    t = GraspTable({"a": np.zeros(2)})
    with pytest.raises(InputError):
        t.with_columns(b=np.zeros(4))


def test_take_selects_rows_of_every_column() -> None:
    t = GraspTable({"a": np.arange(4), "b": np.arange(8).reshape(4, 2)})
    s = t.take(np.array([True, False, True, False]))
    assert len(s) == 2
    np.testing.assert_array_equal(s["b"], [[0, 1], [4, 5]])


def test_missing_column_names_the_columns() -> None:
    t = GraspTable({"dq": np.zeros((1, 8))})
    with pytest.raises(KeyError, match="columns: dq"):
        t["reachable"]
    assert "reachable" not in t
    assert t.get("reachable") is None


def test_the_column_registry_is_complete_and_its_csv_cells_are_unique() -> None:
    from gcm_pipeline.table import CANDIDATE_COLUMNS, COLUMNS

    cells = [c for col in COLUMNS.values() for c in col.csv]
    assert len(cells) == len(set(cells)), cells
    for name, col in COLUMNS.items():
        assert col.dtype in ("float", "int", "bool", "str"), name
        assert col.shape.startswith("(N") and col.stage and col.meaning, name
        assert name not in CANDIDATE_COLUMNS, name
        # a cell names this column or none: no cell is another column's name
        assert not set(col.csv) & (set(COLUMNS) - {name}), name
        if any("{j}" in c for c in col.csv):  # per-joint: the one cell of an (N, nq) column
            assert col.csv == ("q{j}",) and col.shape == "(N, nq)", name
        elif col.shape == "(N,)":  # a 1-D column is one cell (dq: position and quaternion)
            assert len(col.csv) <= 1, name
    # the leading columns come first, in grasps.csv's order
    leading = [bool(col.csv) for col in COLUMNS.values()]
    assert leading == sorted(leading, reverse=True)
