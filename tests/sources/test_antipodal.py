"""Antipodal sampler: every grasp is antipodal, fits the gripper and clears object and table.

Checked against the primitives' exact geometry (not trimesh's): box faces and
normals, the cylinder's surface, and the open Franka hand's measured boxes.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from gcm_pipeline.config import Config
from gcm_pipeline.config.gripper_spec import load_gripper
from gcm_pipeline.errors import ConfigError, InputError
from gcm_pipeline.geometry.dualquat import dq_to_matrix
from gcm_pipeline.pipeline import generate_candidates
from gcm_pipeline.sources.antipodal import _gripper_points

PANDA = load_gripper("franka_panda")
MU = 0.5


def config(obj: dict, **cand) -> Config:
    return Config.from_dict(
        {
            "object": obj,
            "candidates": {"source": "antipodal", "count": 60, "gripper": "franka_panda", **cand},
        }
    )


def to_local(cfg: Config, poses: np.ndarray) -> np.ndarray:
    return np.linalg.inv(cfg.object.pose.matrix()) @ poses


def hand_points(poses: np.ndarray) -> np.ndarray:
    pts = np.concatenate(_gripper_points(PANDA))
    return np.einsum("nij,kj->nki", poses[:, :3, :3], pts) + poses[:, None, :3, 3]


def test_box_grasps_are_antipodal_and_clear_the_box():
    size = np.array([0.05, 0.07, 0.12])
    cfg = config(
        {"shape": "box", "dims": {"size": size.tolist()}, "pose": {"xyz": [0.5, 0.1, 0.06]}}
    )
    table = generate_candidates(cfg)
    assert len(table) == 60
    poses = to_local(cfg, dq_to_matrix(table["dq"]))
    y, z, p = poses[:, :3, 1], poses[:, :3, 2], poses[:, :3, 3]
    np.testing.assert_allclose(np.einsum("ij,ij->i", y, z), 0.0, atol=1e-9)  # approach _|_ closing
    # the closing axis lies inside the friction cone of the two opposite faces it meets:
    # within atan(mu) of a box axis, and the contacts are on the two faces of that axis
    axis = np.argmax(np.abs(y), axis=1)
    assert (np.abs(y[np.arange(60), axis]) >= math.cos(math.atan(MU)) - 1e-9).all()
    width = table["width"]
    assert (width <= PANDA.max_width).all() and (width > 0).all()
    np.testing.assert_allclose(width * np.abs(y[np.arange(60), axis]), size[axis], rtol=1e-6)
    # the contacts' midpoint sits finger_depth / 2 behind the fingertip midpoint
    center = p - 0.5 * PANDA.finger_depth * z
    assert (np.abs(center) <= size / 2 + 1e-9).all()
    # the open hand (fingers and palm) is outside the box, and above the table
    pts = hand_points(poses)
    inside = (np.abs(pts) < size / 2 - 1e-6).all(axis=2)
    assert not inside.any()
    world = dq_to_matrix(table["dq"])
    assert (hand_points(world)[..., 2] >= 0.0 - 1e-9).all()
    assert ((table["score"] >= math.cos(math.atan(MU)) - 1e-9) & (table["score"] <= 1)).all()


def test_cylinder_grasps_fit_the_opening_and_clear_the_surface():
    r, h = 0.035, 0.22
    cfg = config(
        {"shape": "cylinder", "dims": {"radius": r, "height": h}, "pose": {"xyz": [0.5, 0, 0]}}
    )
    table = generate_candidates(cfg)
    poses = to_local(cfg, dq_to_matrix(table["dq"]))
    pts = hand_points(poses)
    radial = np.linalg.norm(pts[..., :2], axis=2)
    # the mesh is a 64-gon inscribed in the circle: allow its sagitta
    sag = r * (1 - math.cos(math.pi / 64))
    inside = (radial < r - sag - 1e-6) & (pts[..., 2] > 1e-6) & (pts[..., 2] < h - 1e-6)
    assert not inside.any()
    assert (table["width"] <= PANDA.max_width - 0.005 + 1e-9).all()


def test_same_seed_same_grasps_and_plane_is_rejected():
    cyl = {"shape": "cylinder", "dims": {"radius": 0.03, "height": 0.1}}
    a = generate_candidates(config(cyl, seed=3))
    b = generate_candidates(config(cyl, seed=3))
    np.testing.assert_array_equal(a["dq"], b["dq"])
    with pytest.raises(ConfigError, match="plane has no two sides"):
        generate_candidates(config({"shape": "plane", "dims": {"size": [0.2, 0.2]}}))
    with pytest.raises(ConfigError, match="unknown gripper 'robotiq'.*franka_panda"):
        config(cyl, gripper="robotiq")


def test_many_grasps_keep_memory_flat():
    """The hand's check points are made for a few thousand grasps at a time: 2,000 grasps on
    a box stay far below the ~570 MB that checking every candidate pose at once took."""
    import tracemalloc

    box = {"shape": "box", "dims": {"size": [0.05, 0.05, 0.05]}, "pose": {"xyz": [0.5, 0, 0.025]}}
    tracemalloc.start()
    try:
        table = generate_candidates(config(box, count=2000))
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert len(table) == 2000
    assert peak < 150e6, f"peak {peak / 1e6:.0f} MB"


def test_a_mesh_wound_inside_out_is_sampled_like_the_right_one(tmp_path):
    """Faces wound inside out make every normal point into the object: the rays to the
    opposite contact left the mesh and no grasp was found."""
    import trimesh

    box = trimesh.creation.box(extents=[0.05, 0.04, 0.06])
    right, wrong = tmp_path / "right.obj", tmp_path / "wrong.obj"
    box.export(right)
    box.invert()
    box.export(wrong)
    obj = {"shape": "mesh", "pose": {"xyz": [0.5, 0, 0.03]}}
    a = generate_candidates(config({**obj, "mesh": str(right)}))
    b = generate_candidates(config({**obj, "mesh": str(wrong)}))
    assert len(a) == len(b) == 60
    np.testing.assert_allclose(np.sort(a["width"]), np.sort(b["width"]), atol=1e-9)


@pytest.mark.parametrize(
    ("obj", "size"),
    [
        ({"shape": "sphere", "dims": {"radius": 0.0005}}, "1 x 1 x 1 mm"),
        ({"shape": "sphere", "dims": {"radius": 0.2}}, "400 x 400 x 400 mm"),
    ],
)
def test_no_grasp_says_what_the_fingers_need(obj, size):
    with pytest.raises(InputError) as info:
        generate_candidates(config({**obj, "pose": {"xyz": [0.5, 0, 0.3]}}))
    msg = str(info.value)
    assert size in msg and "2 to 75 mm apart" in msg and "friction cone" in msg, msg
