"""Candidate stage: generators (geometry invariants) and grasp file import."""

from __future__ import annotations

import sys

import numpy as np
import pytest

from gcm_pipeline.config import Config, Pose
from gcm_pipeline.errors import ConfigError, InputError
from gcm_pipeline.geometry.dualquat import dq_to_matrix
from gcm_pipeline.pipeline import candidate_poses, generate_candidates
from gcm_pipeline.sources.files import ACRONYM_INSTALL_HINT, load_grasp_file
from gcm_pipeline.table import GraspTable

OBJECTS = {
    "plane": {"shape": "plane", "dims": {"size": [0.3, 0.2]}},
    "cylinder_side": {"shape": "cylinder", "dims": {"radius": 0.035, "height": 0.22}},
    "box": {"shape": "box", "dims": {"size": [0.06, 0.1, 0.15]}},
    "sphere": {"shape": "sphere", "dims": {"radius": 0.05}},
}
OBJECT_POSE = {"xyz": [0.5, -0.1, 0.2], "rpy_deg": [10, -20, 35]}


def _cfg(source, *, pose=None, noise=None, count=30, seed=None, cand_seed=None, **extra):
    obj = dict(OBJECTS[source])
    if pose is not None:
        obj["pose"] = pose
    cand = {"source": source, "count": count, **extra}
    if cand_seed is not None:
        cand["seed"] = cand_seed
    if noise is not None:
        cand["noise"] = noise
    data = {"object": obj, "candidates": cand}
    if seed is not None:
        data["seed"] = seed
    return Config.from_dict(data)


def grasp_poses(cfg):
    """World poses (N, 4, 4) of a config's candidates."""
    return candidate_poses(cfg)[0]


def _local(cfg):
    """Poses in the object frame."""
    return np.linalg.inv(cfg.object.pose.matrix()) @ grasp_poses(cfg)


def _assert_rigid(poses):
    rot = poses[:, :3, :3]
    assert np.allclose(rot @ np.swapaxes(rot, 1, 2), np.eye(3), atol=1e-12)
    assert np.allclose(np.linalg.det(rot), 1.0)
    assert np.allclose(poses[:, 3], [0, 0, 0, 1])


@pytest.mark.parametrize("source", sorted(OBJECTS))
def test_generators_give_unit_dual_quaternions(source):
    cfg = _cfg(source, pose=OBJECT_POSE, noise={"position": 0.002, "angle_deg": 3})
    table = generate_candidates(cfg)
    assert isinstance(table, GraspTable) and table.columns == ("dq",)
    dq = table["dq"]
    assert dq.shape == (30, 8)
    assert np.allclose(np.linalg.norm(dq[:, :4], axis=1), 1.0)
    assert np.allclose(np.einsum("ij,ij->i", dq[:, :4], dq[:, 4:]), 0.0, atol=1e-12)
    poses = grasp_poses(cfg)
    _assert_rigid(poses)
    assert np.allclose(dq_to_matrix(dq), poses, atol=1e-12)


@pytest.mark.parametrize("source", sorted(OBJECTS))
def test_same_seed_same_grasps_other_seed_other_noise(source):
    noise = {"position": 0.002, "angle_deg": 3}
    a = generate_candidates(_cfg(source, noise=noise, seed=4))["dq"]
    b = generate_candidates(_cfg(source, noise=noise, seed=4))["dq"]
    c = generate_candidates(_cfg(source, noise=noise, seed=5))["dq"]
    assert np.array_equal(a, b)
    assert not np.allclose(a, c)
    # candidates.seed wins over the top-level seed
    d = generate_candidates(_cfg(source, noise=noise, seed=5, cand_seed=4))["dq"]
    assert np.array_equal(a, d)


@pytest.mark.parametrize("source", sorted(OBJECTS))
def test_object_pose_maps_object_frame_to_world(source):
    plain = grasp_poses(_cfg(source, seed=2))
    moved_cfg = _cfg(source, pose=OBJECT_POSE, seed=2)
    moved = grasp_poses(moved_cfg)
    assert np.allclose(moved, moved_cfg.object.pose.matrix() @ plain, atol=1e-12)


def test_plane_grasps_come_from_above():
    cfg = _cfg("plane", pose={"xyz": [0.4, 0.0, 0.1]})
    poses = grasp_poses(cfg)
    assert np.allclose(poses[:, :3, 2], [0, 0, -1])  # approach straight down
    assert np.allclose(poses[:, 2, 3], 0.1)  # on the surface (depth 0)
    assert np.all(np.abs(poses[:, 0, 3] - 0.4) <= 0.4 * 0.3 + 1e-12)
    assert np.all(np.abs(poses[:, 1, 3]) <= 0.4 * 0.2 + 1e-12)
    # a tilted plane: the approach follows the plane's normal
    tilted = _cfg("plane", pose={"rpy_deg": [30, 0, 0]})
    normal = tilted.object.pose.matrix()[:3, 2]
    assert np.allclose(grasp_poses(tilted)[:, :3, 2], -normal)


def test_cylinder_side_is_radial_and_tangential():
    r, h, depth = 0.035, 0.22, 0.01
    cfg = _cfg("cylinder_side", count=36, rings=3)
    poses = _local(cfg)
    p, x, y, z = poses[:, :3, 3], poses[:, :3, 0], poses[:, :3, 1], poses[:, :3, 2]
    radial = p[:, :2] / np.linalg.norm(p[:, :2], axis=1, keepdims=True)
    assert np.allclose(np.linalg.norm(p[:, :2], axis=1), r - depth)
    assert np.allclose(z[:, :2], -radial) and np.allclose(z[:, 2], 0)  # toward the axis
    tangent = np.column_stack([-radial[:, 1], radial[:, 0]])
    assert np.allclose(y[:, :2], tangent) and np.allclose(y[:, 2], 0)  # closing tangential
    assert np.allclose(x, [0, 0, 1])
    heights = np.unique(p[:, 2].round(9))
    assert np.allclose(heights, [0.2 * h, 0.5 * h, 0.8 * h])
    assert np.all(np.bincount(np.searchsorted(heights, p[:, 2].round(9))) == 12)


def test_box_grasps_approach_along_inward_face_normals():
    size = np.array([0.06, 0.1, 0.15])
    poses = _local(_cfg("box", count=200, seed=1))
    p, y, z = poses[:, :3, 3], poses[:, :3, 1], poses[:, :3, 2]
    axis = np.argmax(np.abs(z), axis=1)
    assert np.allclose(np.abs(z[np.arange(200), axis]), 1.0)
    outward = -z
    # never the face the box stands on (-z)
    assert not np.any((axis == 2) & (outward[:, 2] < 0))
    # on the face plane, 1 cm past it
    assert np.allclose(np.einsum("ij,ij->i", p, outward), size[axis] / 2 - 0.01)
    # fingers close along the face's shorter side
    close = np.argmax(np.abs(y), axis=1)
    for f in range(3):
        sel = axis == f
        others = [i for i in range(3) if i != f]
        assert np.all(close[sel] == others[int(np.argmin(size[others]))])
    assert len(np.unique(axis)) == 3  # all face directions used


def test_sphere_grasps_point_at_the_centre():
    r, depth = 0.05, 0.01
    poses = _local(_cfg("sphere", count=50))
    p, z = poses[:, :3, 3], poses[:, :3, 2]
    assert np.allclose(p + (r - depth) * z, 0.0, atol=1e-12)
    polar = np.degrees(np.arccos(np.clip(-z[:, 2], -1, 1)))
    assert polar.max() <= 120.0 + 1e-9
    assert np.allclose(poses[:, 2, 1], 0.0)  # fingers close horizontally


def test_noise_magnitudes():
    base = grasp_poses(_cfg("cylinder_side", count=400))
    noisy = grasp_poses(_cfg("cylinder_side", count=400, noise={"position": 0.003, "angle_deg": 4}))
    dp = noisy[:, :3, 3] - base[:, :3, 3]
    assert 0.0025 < dp.std() < 0.0035
    rel = np.swapaxes(base[:, :3, :3], 1, 2) @ noisy[:, :3, :3]
    angle = np.degrees(np.arccos(np.clip((np.trace(rel, axis1=1, axis2=2) - 1) / 2, -1, 1)))
    # |N(0, 4 deg)| has mean 4 * sqrt(2 / pi) ~ 3.19 deg
    assert 2.7 < angle.mean() < 3.7


def test_depth_option_moves_along_the_approach():
    a = _local(_cfg("cylinder_side", count=12, rings=2, depth=0.0))
    b = _local(_cfg("cylinder_side", count=12, rings=2, depth=0.02))
    assert np.allclose(b[:, :3, 3] - a[:, :3, 3], 0.02 * a[:, :3, 2])


# ------------------------------------------------------------------ files


def _random_poses(n, seed=0):
    rng = np.random.default_rng(seed)
    from scipy.spatial.transform import Rotation

    t = np.zeros((n, 4, 4))
    t[:, :3, :3] = Rotation.random(n, random_state=seed).as_matrix()
    t[:, :3, 3] = rng.uniform(-0.1, 0.1, size=(n, 3))
    t[:, 3, 3] = 1
    return t


def _file_cfg(path, **cand):
    data = {"candidates": {"source": "file", "path": str(path), **cand}}
    if cand.get("frame") == "object":
        data["object"] = {
            "shape": "cylinder",
            "dims": {"radius": 0.04, "height": 0.1},
            "pose": OBJECT_POSE,
        }
    return Config.from_dict(data)


def test_npy_world_and_object_frames(tmp_path):
    poses = _random_poses(7)
    path = tmp_path / "g.npy"
    np.save(path, poses)
    assert np.allclose(grasp_poses(_file_cfg(path)), poses)
    cfg = _file_cfg(path, frame="object")
    assert np.allclose(grasp_poses(cfg), cfg.object.pose.matrix() @ poses)
    table = generate_candidates(cfg)
    assert np.allclose(dq_to_matrix(table["dq"]), cfg.object.pose.matrix() @ poses)


def test_grasp_to_tool_is_applied_on_the_right(tmp_path):
    poses = _random_poses(5)
    path = tmp_path / "g.npy"
    np.save(path, poses)
    g2t = {"xyz": [0, 0, 0.1034], "rpy_deg": [0, 0, -90]}
    got = grasp_poses(_file_cfg(path, grasp_to_tool=g2t))
    assert np.allclose(got, poses @ Pose(**g2t).matrix())


def test_acronym_grasp_to_tool_geometry():
    """ACRONYM's Franka frame: hand base, fingers along x; tcp 0.1034 m ahead, fingers along y."""
    tool = Pose(xyz=(0, 0, 0.1034), rpy_deg=(0, 0, -90)).matrix()
    # finger pad centres of ACRONYM's Franka gripper (open), in its gripper frame
    fingers = np.array([[0.041, 0, 0.1034], [-0.041, 0, 0.1034]])
    assert np.allclose(tool[:3, 3], fingers.mean(axis=0))  # tcp between the fingertips
    assert np.allclose(tool[:3, 1], [1, 0, 0])  # tool y = gripper +x: the closing axis
    assert np.allclose(tool[:3, 2], [0, 0, 1])  # same approach
    flipped = Pose(xyz=(0, 0, 0.1034), rpy_deg=(0, 0, 90)).matrix()
    assert np.allclose(flipped[:3, 1], [-1, 0, 0])  # +90: same grasp turned by 180 deg


def test_npz_with_success_and_limit(tmp_path):
    poses = _random_poses(10)
    success = np.array([1, 0, 1, 1, 0, 0, 1, 1, 1, 0])
    path = tmp_path / "g.npz"
    np.savez(path, transforms=poses, success=success)
    got = load_grasp_file(path, success_only=True, limit=3)
    assert np.allclose(got, poses[success == 1][:3])
    assert load_grasp_file(path).shape == (10, 4, 4)


def test_csv_import(tmp_path):
    from scipy.spatial.transform import Rotation

    poses = _random_poses(6)
    q = Rotation.from_matrix(poses[:, :3, :3]).as_quat()[:, [3, 0, 1, 2]]
    path = tmp_path / "g.csv"
    lines = ["id,qw,qx,qy,qz,x,y,z,success"]
    for i in range(6):
        vals = [*q[i], *poses[i, :3, 3]]
        lines.append(f"{i}," + ",".join(repr(float(v)) for v in vals) + f",{i % 2}")
    path.write_text("\n".join(lines) + "\n")
    assert np.allclose(load_grasp_file(path), poses, atol=1e-12)
    assert np.allclose(load_grasp_file(path, success_only=True), poses[1::2], atol=1e-12)


def _write_acronym(path, poses, success, *, drop=None):
    import h5py

    with h5py.File(path, "w") as f:
        if drop != "grasps/transforms":
            f["grasps/transforms"] = poses
        if drop != "grasps/qualities/flex/object_in_gripper":
            f["grasps/qualities/flex/object_in_gripper"] = success
        f["object/file"] = "meshes/Mug/abc.obj"
        f["object/scale"] = 0.8


def test_acronym_import(tmp_path):
    pytest.importorskip("h5py")
    poses = _random_poses(12)
    success = (np.arange(12) % 3 != 0).astype(np.int64)
    path = tmp_path / "Mug_abc_0.8.h5"
    _write_acronym(path, poses, success)
    assert np.allclose(load_grasp_file(path), poses)
    got = load_grasp_file(path, format="acronym", success_only=True, limit=5)
    assert np.allclose(got, poses[success == 1][:5])
    cfg = _file_cfg(
        path,
        format="acronym",
        frame="object",
        success_only=True,
        grasp_to_tool={"xyz": [0, 0, 0.1034], "rpy_deg": [0, 0, -90]},
    )
    table = generate_candidates(cfg)
    expected = (
        cfg.object.pose.matrix() @ poses[success == 1] @ cfg.candidates.grasp_to_tool.matrix()
    )
    assert np.allclose(dq_to_matrix(table["dq"]), expected)
    assert table["source_id"].tolist() == np.flatnonzero(success == 1).tolist()
    # with a gripper instead of grasp_to_tool: the same poses, the same source rows
    by_gripper = generate_candidates(
        _file_cfg(path, format="acronym", frame="object", success_only=True, gripper="franka_panda")
    )
    assert np.allclose(dq_to_matrix(by_gripper["dq"]), expected, atol=1e-9)
    assert by_gripper["source_id"].tolist() == table["source_id"].tolist()


@pytest.mark.parametrize("key", ["grasps/transforms", "grasps/qualities/flex/object_in_gripper"])
def test_acronym_missing_key(tmp_path, key):
    pytest.importorskip("h5py")
    path = tmp_path / "bad.h5"
    _write_acronym(path, _random_poses(3), np.ones(3), drop=key)
    with pytest.raises(InputError, match=f"missing dataset '{key}'"):
        load_grasp_file(path)


def test_acronym_without_h5py_names_the_extra(tmp_path, monkeypatch):
    path = tmp_path / "g.h5"
    path.write_bytes(b"not really hdf5")
    monkeypatch.setitem(sys.modules, "h5py", None)
    with pytest.raises(InputError) as info:
        load_grasp_file(path)
    assert ACRONYM_INSTALL_HINT in str(info.value)
    assert 'pip install "gcm-pipeline[acronym]"' in str(info.value)


def test_file_errors(tmp_path):
    with pytest.raises(InputError, match="not found"):
        load_grasp_file(tmp_path / "missing.npy")
    wrong = tmp_path / "wrong.npy"
    np.save(wrong, np.zeros((3, 3, 3)))
    with pytest.raises(InputError, match=r"shape \(N, 4, 4\), got \(3, 3, 3\)"):
        load_grasp_file(wrong)
    poses = _random_poses(5)
    poses[3, :3, :3] *= 1.5
    bad = tmp_path / "scaled.npy"
    np.save(bad, poses)
    with pytest.raises(InputError, match="grasp 3 .* not a rigid transform"):
        load_grasp_file(bad)
    poses = _random_poses(5)
    poses[2, :3, 0] *= -1
    refl = tmp_path / "refl.npy"
    np.save(refl, poses)
    with pytest.raises(InputError, match="grasp 2 .*reflection"):
        load_grasp_file(refl)
    poses = _random_poses(5)
    poses[4, 3] = [0, 0, 1, 1]
    bottom = tmp_path / "bottom.npy"
    np.save(bottom, poses)
    with pytest.raises(InputError, match="grasp 4 .*last row"):
        load_grasp_file(bottom)
    noext = tmp_path / "grasps.txt"
    noext.write_text("x")
    with pytest.raises(InputError, match="set candidates.format"):
        load_grasp_file(noext)
    nosucc = tmp_path / "plain.npy"
    np.save(nosucc, _random_poses(2))
    with pytest.raises(InputError, match="success labels"):
        load_grasp_file(nosucc, success_only=True)


def test_csv_errors(tmp_path):
    path = tmp_path / "g.csv"
    path.write_text("x,y,z,qw,qx,qy\n0,0,0,1,0,0\n")
    with pytest.raises(InputError, match="lacks column"):
        load_grasp_file(path)
    path.write_text("x,y,z,qw,qx,qy,qz\n0,0,0,1,0,0,0\n0,0,0,2,0,0,0\n")
    with pytest.raises(InputError, match=r"g\.csv:3: quaternion"):
        load_grasp_file(path)
    path.write_text("x,y,z,qw,qx,qy,qz\n0,0,0,1,0,0,0\n0,a,0,1,0,0,0\n")
    with pytest.raises(InputError, match=r"g\.csv:3: column .y.: not a number"):
        load_grasp_file(path)


def test_generator_needs_matching_object():
    with pytest.raises(ConfigError, match="needs object.shape 'plane'"):
        Config.from_dict({"candidates": {"source": "plane"}})


def test_no_grasp_left_is_an_error(tmp_path):
    path = tmp_path / "g.npz"
    np.savez(path, transforms=np.zeros((0, 4, 4)), success=np.zeros(0))
    with pytest.raises(InputError, match="no grasp left"):
        generate_candidates(_file_cfg(path, success_only=True))
    np.savez(path, transforms=_random_poses(3), success=np.zeros(3))
    with pytest.raises(InputError, match="none of its 3 grasps is labelled successful"):
        generate_candidates(_file_cfg(path, success_only=True))


def test_default_rings_space_grasps_evenly():
    poses = _local(_cfg("cylinder_side", count=72))
    heights = np.unique(poses[:, 2, 3].round(9))
    assert len(heights) == 8  # 8 rings of 9: 40 deg x 25 mm ~ 17 mm, rings 19 mm apart


def test_depth_past_the_centre_is_an_error():
    with pytest.raises(ConfigError, match="candidates.depth .* must not exceed the radius"):
        generate_candidates(_cfg("cylinder_side", depth=0.05))


def test_depth_equal_to_the_radius_puts_the_tool_points_on_the_axis():
    cfg = _cfg("cylinder_side", count=12, rings=2)
    radius = cfg.object.dims.radius
    poses = _local(_cfg("cylinder_side", count=12, rings=2, depth=radius))
    np.testing.assert_allclose(poses[:, :2, 3], 0.0, atol=1e-12)  # on the axis
    _assert_rigid(poses)
    with pytest.raises(ConfigError, match="candidates.depth"):
        generate_candidates(_cfg("cylinder_side", depth=radius + 1e-6))
