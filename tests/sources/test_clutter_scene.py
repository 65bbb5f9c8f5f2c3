"""The rendered clutter scene (tests/data/clutter, scripts/make_clutter_scene.py) is what it says.

Its depth image, intrinsics and camera pose must put every pixel back on
the surface of the object its segmentation names, its grasps' contact
points on the mug, and the command its README gives must rebuild it.
"""

from __future__ import annotations

import importlib.util
import json
import subprocess
import sys

import numpy as np
import pytest
import trimesh
from helpers import DATA, ROOT, gcm_env

from gcm_pipeline.config.sections import Pose
from gcm_pipeline.sources.files.pickled import read_npz_members

CLUTTER = DATA / "clutter"
SCRIPT = ROOT / "scripts" / "make_clutter_scene.py"


@pytest.fixture(scope="module")
def script():
    spec = importlib.util.spec_from_file_location("make_clutter_scene", SCRIPT)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


@pytest.fixture(scope="module")
def scene():
    with np.load(CLUTTER / "scene.npz") as z:
        arrays = {k: z[k] for k in z.files}
    return arrays, json.loads((CLUTTER / "scene.json").read_text())


def camera(meta) -> np.ndarray:
    return Pose(**meta["camera_pose"]).matrix()


def world_points(arrays, meta, rows, cols) -> np.ndarray:
    """Pixels (row, col) back-projected with K and the camera pose into the world."""
    K, z = arrays["K"], arrays["depth"][rows, cols].astype(float)
    cam = np.column_stack([(cols - K[0, 2]) * z / K[0, 0], (rows - K[1, 2]) * z / K[1, 1], z])
    pose = camera(meta)
    return cam @ pose[:3, :3].T + pose[:3, 3]


def test_scene_is_contact_graspnets_input_layout(scene):
    arrays, meta = scene
    assert set(arrays) == {"depth", "K", "segmap", "rgb"}
    h, w = meta["image"]["height"], meta["image"]["width"]
    assert arrays["depth"].shape == arrays["segmap"].shape == (h, w)
    assert arrays["rgb"].shape == (h, w, 3) and arrays["rgb"].dtype == np.uint8
    assert arrays["K"].shape == (3, 3) and arrays["depth"].dtype == np.float32
    depth = arrays["depth"]
    assert np.all(np.isfinite(depth)) and np.all(depth >= 0)
    hit = depth > 0
    assert 0.5 < hit.mean() < 1.0  # the table fills most of the view, the sky the rest
    # the segment ids are the placed objects', each seen, and only where a ray hit
    ids = {o["segment"] for o in meta["objects"]}
    assert set(np.unique(arrays["segmap"][hit]).tolist()) == ids
    assert np.all(arrays["segmap"][~hit] == 0) and np.all(arrays["rgb"][~hit] == 0)
    # BGR as OpenCV reads an image: the red target mug is high in channel 2, the blue one in 0
    bgr = arrays["rgb"].astype(float)
    red, blue = (bgr[arrays["segmap"] == s].mean(axis=0) for s in (1, 2))
    assert red[2] > 2 * red[0] and blue[0] > 2 * blue[2]
    for o in meta["objects"]:
        assert o["pixels"] == np.count_nonzero(arrays["segmap"][hit] == o["segment"]) > 500


def test_pixels_back_project_onto_the_surface_of_their_segment(scene, script):
    arrays, meta = scene
    objects = {o["segment"]: o for o in script.scene_objects()}
    rng = np.random.default_rng(1)
    for o in meta["objects"]:
        seg = o["segment"]
        rows, cols = np.nonzero((arrays["segmap"] == seg) & (arrays["depth"] > 0))
        pick = rng.choice(len(rows), size=min(400, len(rows)), replace=False)
        pts = world_points(arrays, meta, rows[pick], cols[pick])
        mesh = objects[seg]["mesh"].copy()
        np.testing.assert_allclose(objects[seg]["pose"], o["pose"], atol=1e-9)
        mesh.apply_transform(np.asarray(o["pose"]))
        _, dist, _ = trimesh.proximity.closest_point(mesh, pts)
        # depth is stored in 0.1 mm steps; a grazing ray stretches that along the ray
        assert np.percentile(dist, 99) < 1e-3 and dist.max() < 5e-3, (o["name"], dist.max())
    table = np.nonzero((arrays["segmap"] == 0) & (arrays["depth"] > 0))
    pts = world_points(arrays, meta, *table)
    assert np.abs(pts[:, 2]).max() < 2e-3  # the table top is the plane z = 0


def test_grasp_contacts_lie_on_the_mug_between_the_fingers(scene, script):
    _, meta = scene
    pred = read_npz_members(CLUTTER / "predictions.npz", 10_000)
    poses = pred["pred_grasps_cam"].item()[1].astype(float)
    contacts = pred["contact_pts"].item()[1].astype(float)
    assert len(poses) == len(contacts) == meta["grasps"] > 100
    cam = camera(meta)
    world = cam @ poses
    pts = contacts @ cam[:3, :3].T + cam[:3, 3]
    mug = next(o for o in meta["objects"] if o["name"] == "acronym_mug")
    mesh = script.scene_objects()[1]["mesh"].copy()
    mesh.apply_transform(np.asarray(mug["pose"]))
    _, dist, _ = trimesh.proximity.closest_point(mesh, pts)
    assert dist.max() < 1e-4
    # in the hand's frame: on the closing line (y = 0), on the finger pads' depth, on the side of
    # the -x finger (where Contact-GraspNet's predictions put it: x = -width / 2)
    local = np.einsum("nji,nj->ni", world[:, :3, :3], pts - world[:, :3, 3])
    assert np.abs(local[:, 1]).max() < 1e-4
    assert np.all(local[:, 2] <= script.FINGERTIP_Z + 1e-4)
    assert np.all(local[:, 2] >= script.FINGERTIP_Z - script.PAD_LENGTH - 1e-4)
    assert np.all(np.abs(local[:, 0]) <= script.FINGER_X)
    assert np.mean(local[:, 0] <= 1e-3) > 0.95  # past the centre only on a thin wall


def test_the_readme_command_rebuilds_the_scene(tmp_path, scene):
    arrays, meta = scene
    proc = subprocess.run(
        [sys.executable, str(SCRIPT), "--out", str(tmp_path)],
        env=gcm_env(),
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert meta["command"] in (CLUTTER / "README.md").read_text()
    with np.load(tmp_path / "scene.npz") as z:
        # one caster (Embree) or another (trimesh's own) may split a pixel on an edge
        same = z["segmap"] == arrays["segmap"]
        assert same.mean() > 0.995
        np.testing.assert_allclose(z["depth"][same], arrays["depth"][same], atol=2e-4)
        np.testing.assert_array_equal(z["K"], arrays["K"])
    assert json.loads((tmp_path / "scene.json").read_text())["grasps"] == meta["grasps"]


@pytest.mark.parametrize(
    ("args", "fragment"),
    [
        (["--width", "0"], "--width: 0 is not in [1, 4096]"),
        (["--fov", "180"], "--fov: 180 is not in (0, 180)"),
        (["--fov", "nan"], "--fov: nan"),
        (["--grasps", "-1"], "--grasps: -1 is not >= 1"),
        (["--seed", "-1"], "--seed: -1"),
        (["--ply-stride", "0"], "--ply-stride: 0 is not >= 1"),
    ],
)
def test_bad_arguments_are_refused_before_anything_is_written(tmp_path, args, fragment):
    out = tmp_path / "scene"
    proc = subprocess.run(
        [sys.executable, str(SCRIPT), "--out", str(out), *args],
        env=gcm_env(),
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert proc.returncode == 2, proc.stderr[-2000:]
    assert "Traceback" not in proc.stderr
    assert fragment in proc.stderr.splitlines()[-1]
    assert not out.exists()
