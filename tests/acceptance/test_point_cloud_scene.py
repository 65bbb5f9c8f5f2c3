"""A cluttered scene seen by a depth camera, as the only obstacle; every reachable grasp checked.

The scene (a bottle, a box beside it, a ball) is rendered into a depth image
with a segmentation by trimesh's ray casting from a virtual camera, and saved
in Contact-GraspNet's ``.npz`` layout (``depth``, ``K``, ``segmap``, ``rgb``).
``gcm run`` grasps the bottle (a cylinder object) with the cloud as the only
obstacle, its own segment excluded. Then, independently of the package's
reader, voxel grid, tiles and broad phase, every reachable grasp's arm and
gripper (Pinocchio's forward kinematics of the robot's collision geometries,
plain ``coal.collide``) is checked against an octree of the raw depth
points (minus the bottle's segment) at the voxel resolution: 0 collisions.
"""

from __future__ import annotations

import csv
import json

import coal
import numpy as np
import pinocchio as pin
import pytest
import trimesh
import yaml
from helpers import BOTTLE, QUICK, assert_one_line_error, run_gcm
from scipy.spatial.transform import Rotation

from gcm_pipeline.config.robot_spec import load_robot
from gcm_pipeline.config.run import load_config
from gcm_pipeline.config.sections import Pose
from gcm_pipeline.geometry.dualquat import dq_to_matrix
from gcm_pipeline.pipeline import generate_candidates

VOXEL = 0.01
K = np.array([[280.0, 0.0, 160.0], [0.0, 280.0, 120.0], [0.0, 0.0, 1.0]])
H, W = 240, 320
EYE = np.array([0.3, -0.45, 0.55])
BOTTLE_SEGMENT = 1


def _camera() -> tuple[np.ndarray, list[float]]:
    """The camera's pose (4, 4) (OpenCV optical frame) looking at the bottle, and its rpy.

    The pose is the config's (``Pose.matrix`` of the rpy given), as a user gives it.
    """
    z = np.array([0.5, 0.0, 0.1]) - EYE
    z /= np.linalg.norm(z)
    x = np.cross(z, [0.0, 0.0, 1.0])
    x /= np.linalg.norm(x)
    rot = np.stack([x, np.cross(z, x), z], axis=1)
    rpy = Rotation.from_matrix(rot).as_euler("xyz").tolist()
    return Pose(xyz=tuple(EYE.tolist()), rpy=tuple(rpy)).matrix(), rpy


def _render(path) -> np.ndarray:
    """Render the scene into ``path`` (.npz); returns the camera pose."""
    bottle = trimesh.creation.cylinder(0.035, 0.22)
    bottle.apply_translation((0.5, 0.0, 0.11))
    box = trimesh.creation.box((0.06, 0.08, 0.18))
    box.apply_translation((0.5025, 0.115, 0.0925))  # faces off the voxel grid's planes
    ball = trimesh.creation.icosphere(3, 0.05)
    ball.apply_translation((0.56, -0.1, 0.05))
    meshes = [bottle, box, ball]
    scene = trimesh.util.concatenate(meshes)
    segment_of = np.concatenate([np.full(len(m.faces), i + 1) for i, m in enumerate(meshes)])
    pose, _ = _camera()
    v, u = np.mgrid[0:H, 0:W]
    rays = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones((H, W))], -1)
    dirs = rays.reshape(-1, 3) @ pose[:3, :3].T
    eye = pose[:3, 3]
    loc, ray, tri = scene.ray.intersects_location(
        np.tile(eye, (len(dirs), 1)), dirs, multiple_hits=False
    )
    depth = np.zeros(H * W)
    segmap = np.zeros(H * W, dtype=np.int64)
    depth[ray] = (loc - eye) @ pose[:3, 2]
    segmap[ray] = segment_of[tri]
    depth = depth.reshape(H, W)
    depth[0, :5] = np.nan  # a sensor's holes: dropped and counted
    rgb = np.zeros((H, W, 3), np.uint8)
    rgb[..., 0] = 200  # stored BGR: blue
    np.savez(path, depth=depth, K=K, segmap=segmap.reshape(H, W), rgb=rgb)
    return pose


def _raw_points(path, pose) -> np.ndarray:
    """World points of the depth image, minus the bottle's segment (written out here)."""
    data = np.load(path)
    depth, segmap = data["depth"], data["segmap"]
    v, u = np.nonzero(np.isfinite(depth) & (depth > 0) & (segmap != BOTTLE_SEGMENT))
    z = depth[v, u]
    cam = np.stack([(u - K[0, 2]) * z / K[0, 0], (v - K[1, 2]) * z / K[1, 1], z], axis=1)
    return cam @ pose[:3, :3].T + pose[:3, 3]


@pytest.fixture(scope="module")
def scene_run(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("cloud_scene")
    pose = _render(tmp / "scene.npz")
    _, rpy = _camera()
    cfg = yaml.safe_load(BOTTLE.read_text())
    cfg["environment"] = {
        "table": None,
        "point_clouds": [
            {
                "path": "scene.npz",
                "camera_pose": {"xyz": EYE.tolist(), "rpy": rpy},
                "voxel_size": VOXEL,
                "exclude_segments": [BOTTLE_SEGMENT],
            }
        ],
    }
    cfg["densify"] = {"subdivisions": 2, "method": "dlb"}
    cfg["output"] = {"dir": "out"}
    (tmp / "scene.yaml").write_text(yaml.safe_dump(cfg))
    res = run_gcm("run", tmp / "scene.yaml", "-q", *QUICK)
    assert res.returncode == 0, res.stderr
    return tmp, pose


def test_reachable_grasps_do_not_touch_the_raw_cloud(scene_run):
    tmp, pose = scene_run
    out = tmp / "out"
    with open(out / "grasps.csv", newline="") as fh:
        reachable = np.array([row["reachable"] == "true" for row in csv.DictReader(fh)])
    reasons = json.loads((out / "summary.json").read_text())["counts"]["unreachable_by_reason"]
    assert reasons.get("collision_environment", 0) > 10  # the clutter blocks grasps
    assert reachable.sum() > 20
    q = np.load(out / "configurations.npz")["q"][reachable]
    tree = coal.makeOctree(_raw_points(tmp / "scene.npz", pose), VOXEL)
    assert _robot_hits(q, tree) == []


def test_the_run_records_and_saves_the_cloud(scene_run):
    tmp, pose = scene_run
    out = tmp / "out"
    (cloud,) = json.loads((out / "summary.json").read_text())["point_clouds"]
    counts = cloud["counts"]
    assert counts["read"] == H * W
    assert counts["non_finite"] == 5
    seg = np.load(tmp / "scene.npz")["segmap"]
    assert counts["excluded_segments"] == np.count_nonzero(seg == BOTTLE_SEGMENT)
    saved = np.load(out / "cloud.npz")
    assert len(saved["points"]) == counts["voxels"] > 100
    assert BOTTLE_SEGMENT not in set(saved["segments"].tolist())
    assert {2, 3} <= set(saved["segments"].tolist())
    np.testing.assert_array_equal(saved["colors"][0], [0, 0, 200])  # BGR read as RGB
    # every saved voxel holds a raw point (world frame, same grid)
    raw = _raw_points(tmp / "scene.npz", pose)
    keys = {tuple(k) for k in np.floor(raw * (1.0 / VOXEL)).astype(int).tolist()}
    got = {tuple(k) for k in np.floor(saved["points"] / VOXEL).astype(int).tolist()}
    assert got == keys


def test_a_camera_cloud_without_a_pose_is_refused(scene_run):
    tmp, _ = scene_run
    cfg = yaml.safe_load((tmp / "scene.yaml").read_text())
    del cfg["environment"]["point_clouds"][0]["camera_pose"]
    cfg["output"] = {"dir": "refused"}
    (tmp / "nopose.yaml").write_text(yaml.safe_dump(cfg))
    res = run_gcm("run", tmp / "nopose.yaml", "-q", *QUICK)
    assert_one_line_error(res.returncode, res.stderr, "environment.point_clouds[0]", "camera_pose")
    assert not (tmp / "refused").exists()


def _contact_graspnet_run(tmp, name, pose, rpy, **cloud):
    """``gcm run`` of bottle grasps written as Contact-GraspNet predictions (segment 1)."""
    world = dq_to_matrix(generate_candidates(load_config(BOTTLE))["dq"])
    cam = np.linalg.inv(pose) @ world
    pred = np.empty((), dtype=object)
    pred[()] = {BOTTLE_SEGMENT: cam}
    scores = np.empty((), dtype=object)
    scores[()] = {BOTTLE_SEGMENT: np.linspace(0.2, 0.9, len(cam))}
    np.savez(tmp / "pred.npz", pred_grasps_cam=pred, scores=scores)
    cfg = yaml.safe_load((tmp / "scene.yaml").read_text())
    camera = {"xyz": EYE.tolist(), "rpy": rpy}
    cfg["candidates"] = {
        "source": "file",
        "format": "contact_graspnet",
        "path": "pred.npz",
        "camera_pose": camera,
        "grasp_to_tool": {"xyz": [0, 0, 0]},  # the file's poses are the TCP's
    }
    cfg["environment"]["point_clouds"] = [
        {"path": "scene.npz", "voxel_size": VOXEL, **cloud}  # the candidates' camera_pose
    ]
    cfg["output"] = {"dir": name}
    (tmp / f"{name}.yaml").write_text(yaml.safe_dump(cfg))
    res = run_gcm("run", tmp / f"{name}.yaml", "-q", *QUICK)
    assert res.returncode == 0, res.stderr
    return tmp / name


def test_each_contact_graspnet_grasp_is_checked_without_its_own_segment(scene_run):
    tmp, pose = scene_run
    _, rpy = _camera()
    auto = _contact_graspnet_run(tmp, "auto", pose, rpy)
    whole = _contact_graspnet_run(tmp, "whole", pose, rpy, exclude_grasp_segment=False)
    by_hand = _contact_graspnet_run(
        tmp, "by_hand", pose, rpy, exclude_grasp_segment=False, exclude_segments=[BOTTLE_SEGMENT]
    )

    def by_pose(run):
        """reachable, reason, q of each grasp, by its pose (rows are in rank order)."""
        q = np.load(run / "configurations.npz")["q"]
        with open(run / "grasps.csv", newline="") as fh:
            rows = list(csv.DictReader(fh))
        pose = [tuple(r[k] for k in ("x", "y", "z", "qw", "qx", "qy", "qz")) for r in rows]
        return {
            p: (r["reachable"] == "true", r["reason"], qi)
            for p, r, qi in zip(pose, rows, q, strict=True)
        }

    got, alone, hand = by_pose(auto), by_pose(whole), by_pose(by_hand)
    assert got.keys() == alone.keys() == hand.keys()
    assert sum(v[0] for v in got.values()) > 20
    # its own points only block grasps: with them, a reachable grasp may collide
    blocked = [p for p in got if got[p][0] and not alone[p][0]]
    assert not [p for p in got if alone[p][0] and not got[p][0]]
    assert len(blocked) >= 5 and {alone[p][1] for p in blocked} == {"collision_environment"}
    # the same as listing the bottle's segment by hand
    for p, (ok, reason, qi) in got.items():
        assert (ok, reason) == hand[p][:2]
        np.testing.assert_array_equal(qi, hand[p][2])


def _robot_hits(q, tree):
    """(row, geometry) pairs where the robot at ``q`` (M, nq) collides with ``tree`` (coal)."""
    robot = load_robot("panda")
    model, gm = robot.model, robot.build_geometry("collision")
    data, gd = model.createData(), pin.GeometryData(gm)
    identity = coal.Transform3s(np.eye(3), np.zeros(3))
    hits = []
    for i, qi in enumerate(q):
        pin.forwardKinematics(model, data, qi)
        pin.updateGeometryPlacements(model, data, gm, gd)
        for g, go in enumerate(gm.geometryObjects):
            m = gd.oMg[g]
            req, res = coal.CollisionRequest(), coal.CollisionResult()
            tf = coal.Transform3s(m.rotation, m.translation)
            if coal.collide(go.geometry, tf, tree, identity, req, res):
                hits.append((i, go.name))
    return hits


def test_points_near_the_object_are_excluded_by_distance(scene_run):
    """``exclude_object_distance`` instead of the segment: the same check, 0 collisions."""
    tmp, pose = scene_run
    cfg = yaml.safe_load((tmp / "scene.yaml").read_text())
    cloud = cfg["environment"]["point_clouds"][0]
    del cloud["exclude_segments"]
    cloud["exclude_object_distance"] = 0.005
    cfg["output"] = {"dir": "near"}
    (tmp / "near.yaml").write_text(yaml.safe_dump(cfg))
    res = run_gcm("run", tmp / "near.yaml", "-q", *QUICK)
    assert res.returncode == 0, res.stderr
    out = tmp / "near"
    (summary,) = json.loads((out / "summary.json").read_text())["point_clouds"]
    seg = np.load(tmp / "scene.npz")["segmap"]
    # every bottle point, nothing else (the clutter stands centimetres away)
    assert summary["counts"]["excluded_object"] == np.count_nonzero(seg == BOTTLE_SEGMENT)
    with open(out / "grasps.csv", newline="") as fh:
        reachable = np.array([row["reachable"] == "true" for row in csv.DictReader(fh)])
    assert reachable.sum() > 20
    # the raw points minus those within 5 mm of the bottle (a solid cylinder), by hand
    data = np.load(tmp / "scene.npz")
    depth = data["depth"]
    v, u = np.nonzero(np.isfinite(depth) & (depth > 0))
    z = depth[v, u]
    cam = np.stack([(u - K[0, 2]) * z / K[0, 0], (v - K[1, 2]) * z / K[1, 1], z], axis=1)
    world = cam @ pose[:3, :3].T + pose[:3, 3]
    radial = np.maximum(np.hypot(world[:, 0] - 0.5, world[:, 1]) - 0.035, 0.0)
    axial = np.maximum(np.abs(world[:, 2] - 0.11) - 0.11, 0.0)
    far = np.hypot(radial, axial) > 0.005
    q = np.load(out / "configurations.npz")["q"][reachable]
    assert _robot_hits(q, coal.makeOctree(world[far], VOXEL)) == []
