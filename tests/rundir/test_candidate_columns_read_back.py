"""``score`` and ``width`` in a run's ``grasps.csv`` are read back as numbers, or refused by line.

They are the blended per-candidate columns (floats by the table's contract);
a cell that is not a number (a hand edit, or a run of a grasp file whose
width column was text) is one line naming the line and the column, not text
that the MoveIt and ROS 2 bag exports then die on.
"""

from __future__ import annotations

import shutil

import numpy as np
import pytest
from helpers import assert_one_line_error

from gcm_pipeline.errors import InputError
from gcm_pipeline.rundir.grasps_csv import read_grasps_csv


def _add_column(csv_path, name: str, cell: str) -> None:
    lines = csv_path.read_text().splitlines()
    lines = [f"{lines[0]},{name}"] + [f"{ln},{cell}" for ln in lines[1:]]
    csv_path.write_text("\n".join(lines) + "\n")


@pytest.mark.parametrize("name", ["score", "width"])
def test_a_text_cell_of_a_blended_column_names_its_line(tmp_path, flat_run, name):
    path = tmp_path / "grasps.csv"
    shutil.copy(flat_run / "grasps.csv", path)
    _add_column(path, name, "wide")
    with pytest.raises(InputError, match=rf"grasps\.csv:2: column '{name}': not a number: 'wide'"):
        read_grasps_csv(path)


def test_numbers_and_empty_cells_read_as_floats(tmp_path, flat_run):
    path = tmp_path / "grasps.csv"
    shutil.copy(flat_run / "grasps.csv", path)
    _add_column(path, "width", "")
    _add_column(path, "score", "1")
    table = read_grasps_csv(path)
    assert table["width"].dtype == np.float64 and np.isnan(table["width"]).all()
    assert table["score"].dtype == np.float64 and (table["score"] == 1.0).all()


@pytest.mark.parametrize("fmt", ["moveit", "mcap"])
def test_export_of_a_run_with_a_text_width_is_one_line(cli, tmp_path, flat_run, fmt):
    if fmt == "mcap":
        pytest.importorskip("rosbags")
    d = tmp_path / "run"
    shutil.copytree(flat_run, d)
    _add_column(d / "grasps.csv", "width", "wide")
    code, _, err = cli("export", d, "--format", fmt, "--out", tmp_path / f"g.{fmt}")
    assert_one_line_error(code, err, "grasps.csv:2: column 'width': not a number: 'wide'")
    assert not (tmp_path / f"g.{fmt}").exists()
