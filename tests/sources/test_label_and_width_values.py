"""A file's success labels, finger widths and GraspNet rows are read as stated, never guessed.

A success label is 0 or 1 (a 0.5 or a 7 is a broken export, not a grasp to
keep or drop by a threshold); a finger width is a number of metres, not
negative or infinite (an empty CSV cell or a NaN: unknown); a GraspNet row's
``depth`` cannot carry its grasp past the 1,000 m bound its centre obeys, and
its ``object_id`` is a whole number. Each is one line naming the file and the
row, at read time: nothing downstream (the MoveIt export's finger postures)
sees it.
"""

from __future__ import annotations

import numpy as np
import pytest
from helpers import ROOT, assert_one_line_error

from gcm_pipeline.errors import InputError
from gcm_pipeline.sources.files import read_grasps

HEADER = "x,y,z,qw,qx,qy,qz"
ROW = "0.4,0,0.3,0,1,0,0"  # a rigid pose (half a turn about x)


def _csv(tmp_path, column: str, cells: list[str]):
    lines = [f"{HEADER},{column}"] + [f"{ROW},{c}" for c in cells]
    path = tmp_path / "g.csv"
    path.write_text("\n".join(lines) + "\n")
    return path


def _poses(n: int) -> np.ndarray:
    t = np.tile(np.eye(4), (n, 1, 1))
    t[:, :3, :3] = np.diag([1.0, -1.0, -1.0])
    t[:, 0, 3] = 0.4 + 0.01 * np.arange(n)
    t[:, 2, 3] = 0.3
    return t


@pytest.mark.parametrize("label", ["0.5", "2", "-1", "0.9999"])
def test_a_csv_success_label_other_than_0_or_1_names_its_line(tmp_path, label):
    path = _csv(tmp_path, "success", ["1", "0", label])
    with pytest.raises(InputError) as info:
        read_grasps(path, "csv")
    msg = str(info.value)
    assert f"{path}:4: column 'success'" in msg and "0 or 1" in msg, msg
    assert "\n" not in msg


def test_an_npz_success_array_of_probabilities_is_refused(tmp_path):
    path = tmp_path / "g.npz"
    np.savez(path, transforms=_poses(4), success=np.array([1.0, 0.0, 0.3, 0.8]))
    with pytest.raises(InputError, match=r"array 'success': grasp 2 \(0-based\).*0 or 1"):
        read_grasps(path, "npz")


def test_an_acronym_label_of_7_is_refused(tmp_path):
    h5py = pytest.importorskip("h5py")
    src = ROOT / "tests/data/acronym/Mug_10f6e09036350e92b3f21f1137c3c347_0.0002682457830986903.h5"
    path = tmp_path / "mug.h5"
    path.write_bytes(src.read_bytes())
    with h5py.File(path, "r+") as f:
        labels = f["grasps/qualities/flex/object_in_gripper"][()]
        labels[4] = 7
        del f["grasps/qualities/flex/object_in_gripper"]
        f["grasps/qualities/flex/object_in_gripper"] = labels
    with pytest.raises(InputError, match=r"grasp 4 \(0-based\).*0 or 1"):
        read_grasps(path, "acronym")


def test_labels_of_0_and_1_in_any_dtype_are_read(tmp_path):
    for dtype in (bool, np.int8, np.float32, np.float64):
        path = tmp_path / f"g_{np.dtype(dtype).name}.npz"
        np.savez(path, transforms=_poses(3), success=np.array([1, 0, 1], dtype=dtype))
        assert read_grasps(path, "npz", success_only=False).success.tolist() == [
            True,
            False,
            True,
        ]


@pytest.mark.parametrize(
    ("cell", "fragment"),
    [("wide", "not a number: 'wide'"), ("-0.01", "width -0.01"), ("inf", "width inf")],
)
def test_a_bad_csv_width_names_its_line(tmp_path, cell, fragment):
    path = _csv(tmp_path, "width", ["0.04", cell])
    with pytest.raises(InputError) as info:
        read_grasps(path, "csv")
    msg = str(info.value)
    assert f"{path}:3: column 'width'" in msg and fragment in msg, msg


def test_an_empty_csv_width_is_unknown(tmp_path):
    grasps = read_grasps(_csv(tmp_path, "width", ["0.04", ""]), "csv")
    assert grasps.columns["width"][0] == 0.04 and np.isnan(grasps.columns["width"][1])


def test_an_npz_width_of_text_is_refused(tmp_path):
    path = tmp_path / "g.npz"
    np.savez(path, transforms=_poses(2), width=np.array(["a", "b"]))
    with pytest.raises(InputError, match=r"g\.npz: array 'width'.*numbers"):
        read_grasps(path, "npz")


def test_a_text_width_never_reaches_the_moveit_export(cli, tmp_path):
    # it used to be carried as text, and `gcm export --format moveit` died in a traceback
    path = _csv(tmp_path, "width", ["wide"] * 3)
    cfg = tmp_path / "c.yaml"
    cfg.write_text(
        f"robot: {{spec: panda}}\ncandidates: {{source: file, path: {path}, format: csv}}\n"
    )
    code, _, err = cli("validate", cfg)
    assert_one_line_error(code, err, f"{path}:2: column 'width'", "not a number")


def _graspnet_rows(n: int = 3) -> np.ndarray:
    rows = np.zeros((n, 17))
    rows[:, 0] = 0.5  # score
    rows[:, 1] = 0.06  # width
    rows[:, 2] = 0.02  # height
    rows[:, 3] = 0.02  # depth
    rows[:, 4:13] = np.eye(3).reshape(-1)
    rows[:, 13:16] = [0.5, 0.0, 0.2]
    rows[:, 16] = 3
    return rows


@pytest.mark.parametrize(
    ("column", "value", "fragment"),
    [
        (1, -0.5, "width -0.5"),
        (3, 2e6, "farther than 1000 m"),
        (16, 2.5, "object_id 2.5 is not an integer id"),
    ],
)
def test_graspnet_values_name_their_row(tmp_path, column, value, fragment):
    rows = _graspnet_rows()
    rows[1, column] = value
    path = tmp_path / "gg.npy"
    np.save(path, rows)
    with pytest.raises(InputError) as info:
        read_grasps(path, "graspnet")
    msg = str(info.value)
    assert str(path) in msg and "row 1 (0-based)" in msg and fragment in msg, msg


def test_contact_graspnet_negative_opening_names_its_segment(tmp_path):
    t = np.eye(4)
    path = tmp_path / "predictions.npz"
    np.savez(
        path,
        pred_grasps_cam={2: np.stack([t, t])},
        gripper_openings={2: np.array([0.05, -0.02])},
    )
    with pytest.raises(InputError, match=r"gripper_openings\[2\]: grasp 1 \(0-based\).*-0\.02"):
        read_grasps(path, "contact_graspnet")
