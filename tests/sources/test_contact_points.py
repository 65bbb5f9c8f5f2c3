"""Contact-GraspNet's contact points: per-candidate columns that move with the grasps."""

from __future__ import annotations

import json

import numpy as np
import pytest
from helpers import DATA, assert_one_line_error

from gcm_pipeline.config import Config, Pose
from gcm_pipeline.errors import InputError
from gcm_pipeline.geometry.dualquat import dq_to_matrix
from gcm_pipeline.manifold.densify import fill_column
from gcm_pipeline.pipeline import generate_candidates
from gcm_pipeline.sources.files import read_contact_graspnet
from gcm_pipeline.sources.files.pickled import read_npz_members
from gcm_pipeline.table import candidate_fill

CLUTTER = DATA / "clutter"
CONTACT = ("contact_x", "contact_y", "contact_z")
SCENE_CAMERA = json.loads((CLUTTER / "scene.json").read_text())["camera_pose"]


def contacts(table) -> np.ndarray:
    return np.column_stack([np.asarray(table[k], dtype=float) for k in CONTACT])


def file_config(path, camera_pose) -> Config:
    return Config.from_dict(
        {
            "object": {"shape": "box", "dims": {"size": [0.05, 0.05, 0.1]}},
            "candidates": {
                "source": "file",
                "path": str(path),
                "format": "contact_graspnet",
                "camera_pose": camera_pose,
            },
        }
    )


def test_the_file_contact_points_become_three_columns_in_the_camera_frame():
    got = read_contact_graspnet(CLUTTER / "predictions.npz")
    raw = read_npz_members(CLUTTER / "predictions.npz", 10_000)["contact_pts"].item()[1]
    assert len(got.poses) == len(raw)
    np.testing.assert_array_equal(contacts(got.columns), raw.astype(float))


def local_contacts(table) -> np.ndarray:
    """Each row's contact point in its grasp's frame."""
    pose = dq_to_matrix(np.asarray(table["dq"]))
    return np.einsum("nji,nj->ni", pose[:, :3, :3], contacts(table) - pose[:, :3, 3])


@pytest.mark.parametrize(
    "camera_pose",
    [
        {"xyz": [0.0, 0.0, 0.0]},
        SCENE_CAMERA,
        {"xyz": [-0.2, 1.5, 0.1], "rpy_deg": [30, -70, 10]},
    ],
)
def test_the_camera_pose_moves_the_contacts_as_it_moves_the_grasps(camera_pose):
    """Each contact is moved by the camera pose and stays put relative to its grasp."""
    in_camera = generate_candidates(file_config(CLUTTER / "predictions.npz", {"xyz": [0, 0, 0]}))
    table = generate_candidates(file_config(CLUTTER / "predictions.npz", camera_pose))
    pose = Pose(**camera_pose).matrix()
    expected = contacts(in_camera) @ pose[:3, :3].T + pose[:3, 3]
    np.testing.assert_allclose(contacts(table), expected, atol=1e-9)
    np.testing.assert_allclose(local_contacts(table), local_contacts(in_camera), atol=1e-6)
    if camera_pose == SCENE_CAMERA:  # the scene's own camera: the contacts land on its mug
        mug = np.asarray(json.loads((CLUTTER / "scene.json").read_text())["objects"][1]["pose"])
        assert np.linalg.norm(contacts(table)[:, :2] - mug[:2, 3], axis=1).max() < 0.07
        assert contacts(table)[:, 2].min() > -1e-3  # above the table top


def test_interpolated_rows_have_no_contact_point():
    assert all(candidate_fill(k) == "missing" for k in CONTACT)
    col = np.array([0.1, 0.2, 0.3])
    filled = fill_column(col, 2, candidate_fill("contact_x"), np.array([[0, 1, 2]] * 2), None)
    assert np.isnan(filled).all()


def test_a_file_without_contact_points_has_no_contact_columns(tmp_path):
    path = tmp_path / "predictions.npz"
    np.savez(path, pred_grasps_cam={1: np.eye(4)[None]})
    assert not set(CONTACT) & set(read_contact_graspnet(path).columns)


@pytest.mark.parametrize(
    "contact_pts, fragment",
    [
        (np.zeros((3, 3)), r"contact_pts\[1\] must be a \(2, 3\) array"),
        (np.zeros((2, 2)), r"contact_pts\[1\] must be a \(2, 3\) array"),
        (np.zeros((3, 2)), r"contact_pts\[1\] must be a \(2, 3\) array"),
        (np.zeros(6), r"contact_pts\[1\] must be a \(2, 3\) array"),
        (np.array([[0, 0, np.inf], [0, 0, 0]]), r"contact_pts\[1\] has an infinite"),
        (np.array([["a", "b", "c"]] * 2), r"contact_pts\[1\] must be numbers"),
    ],
)
def test_contact_points_of_another_shape_are_refused(tmp_path, contact_pts, fragment):
    path = tmp_path / "predictions.npz"
    np.savez(path, pred_grasps_cam={1: np.stack([np.eye(4)] * 2)}, contact_pts={1: contact_pts})
    with pytest.raises(InputError, match=fragment):
        read_contact_graspnet(path)


def test_contact_points_of_a_segment_without_grasps_are_refused(tmp_path):
    """Keys off by one (0.. instead of 1..) would otherwise leave every contact NaN."""
    path = tmp_path / "p.npz"
    poses = {1: np.stack([np.eye(4)] * 2), 2: np.stack([np.eye(4)])}
    np.savez(path, pred_grasps_cam=poses, contact_pts={0: np.zeros((2, 3)), 1: np.zeros((1, 3))})
    with pytest.raises(
        InputError, match=r"contact_pts has segment 0, which pred_grasps_cam has not"
    ):
        read_contact_graspnet(path)


def test_gcm_run_refuses_bad_contact_points_in_one_line(tmp_path, cli):
    path = tmp_path / "predictions.npz"
    np.savez(path, pred_grasps_cam={1: np.stack([np.eye(4)] * 2)}, contact_pts={1: np.zeros(6)})
    cfg = tmp_path / "run.yaml"
    cfg.write_text(
        "object: {shape: box, dims: {size: [0.05, 0.05, 0.1]}, pose: {xyz: [0, 0, 0.05]}}\n"
        f"candidates: {{source: file, path: {path}, format: contact_graspnet, "
        "camera_pose: {xyz: [0.5, 0, 0.8], rpy_deg: [180, 0, 0]}}\n"
    )
    out = tmp_path / "out"
    code, _, err = cli("run", cfg, "--out", out)
    assert_one_line_error(code, err, str(path), "contact_pts[1]", "(2, 3)", "shape (6,)")
    assert not out.exists()
