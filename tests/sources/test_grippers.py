"""The gripper registry's map back from the robot's grasp frame to a file's gripper frame."""

from __future__ import annotations

import numpy as np
import pytest
from helpers import DATA

from gcm_pipeline.config import Config
from gcm_pipeline.config.gripper_spec import load_gripper
from gcm_pipeline.errors import ConfigError
from gcm_pipeline.geometry.dualquat import dq_to_matrix
from gcm_pipeline.pipeline import build_manifold, densify, generate_candidates
from gcm_pipeline.sources.files import read_grasp_file

ACRONYM = DATA / "acronym"
MUG_H5 = ACRONYM / "Mug_10f6e09036350e92b3f21f1137c3c347_0.0002682457830986903.h5"
MUG_POSE = {"xyz": [0.5, -0.1, -0.0514], "rpy_deg": [0, 0, 30]}


@pytest.mark.parametrize(
    ("convention", "depth"),
    [("base", None), ("center", None), ("center", 0.02), ("center", np.array([0.0, 0.01, 0.03]))],
)
def test_from_tool_undoes_to_tool(convention, depth):
    spec = load_gripper("franka_panda")
    to, back = spec.to_tool(convention, depth), spec.from_tool(convention, depth)
    assert back.shape == to.shape
    np.testing.assert_allclose(to @ back, np.broadcast_to(np.eye(4), to.shape), atol=1e-15)
    np.testing.assert_allclose(back @ to, np.broadcast_to(np.eye(4), to.shape), atol=1e-15)


def test_from_tool_names_the_conventions_on_a_bad_one():
    with pytest.raises(ConfigError, match="base.*center"):
        load_gripper("franka_panda").from_tool("tip")


def test_acronym_rows_map_back_to_the_file_and_blends_stay_rigid():
    """An imported ACRONYM mug, placed in the world, comes back to the file's own transforms.

    So a densified row can be put in the file's gripper frame, e.g. to place
    the dataset's gripper mesh at it.
    """
    pytest.importorskip("h5py")
    cfg = Config.from_dict(
        {
            "object": {
                "shape": "cylinder",
                "dims": {"radius": 0.04, "height": 0.1},
                "pose": MUG_POSE,
            },
            "candidates": {
                "source": "file",
                "path": str(MUG_H5),
                "frame": "object",
                "success_only": False,
            },
            "manifold": {"max_edge_length": 0.08, "max_edge_angle_deg": 50},
            "densify": {"subdivisions": 2},
        }
    )
    report: dict = {}
    grasps = generate_candidates(cfg, report=report)
    dense = densify(grasps, build_manifold(grasps, cfg), cfg)
    spec = load_gripper(report["grasp_frame"]["gripper"])
    world = dq_to_matrix(np.asarray(dense["dq"]))
    back = np.linalg.inv(cfg.object.pose.matrix()) @ world @ spec.from_tool("base")

    file_poses, _ = read_grasp_file(MUG_H5)
    cand = np.flatnonzero(np.asarray(dense["origin"]) == "candidate")
    assert len(cand) == len(file_poses) == 2000
    src = np.asarray(dense["source_id"])[cand]
    # the file's rotations are orthonormal to float32 precision; a dual quaternion
    # holds the nearest rotation, a few 1e-11 away
    np.testing.assert_allclose(back[cand], file_poses[src], atol=1e-9)
    # interpolated rows: rigid poses in the file frame, their hand base 0.1034 m
    # behind the grasp frame along the approach
    interp = np.flatnonzero(np.asarray(dense["origin"]) == "interpolated")
    assert len(interp) > 0
    rot = back[interp, :3, :3]
    np.testing.assert_allclose(
        rot @ np.swapaxes(rot, 1, 2), np.broadcast_to(np.eye(3), rot.shape), atol=1e-9
    )
    tcp = np.linalg.inv(cfg.object.pose.matrix()) @ world[interp]
    np.testing.assert_allclose(
        tcp[:, :3, 3], back[interp, :3, 3] + 0.1034 * back[interp, :3, 2], atol=1e-9
    )
