"""The scene's point clouds and contact points: what the meshcat scene tree holds."""

from __future__ import annotations

import base64
import json
import re

import numpy as np
import pytest
import umsgpack
from helpers import DATA

from gcm_pipeline.config import Config, Pose
from gcm_pipeline.errors import PublishError
from gcm_pipeline.outputs.html import render_scene_html
from gcm_pipeline.outputs.scene import SCENE_PATHS, SceneOptions
from gcm_pipeline.outputs.scene_cloud import (
    CONTACT_COLOR,
    MAX_CLOUD_POINTS,
    SceneCloud,
)
from gcm_pipeline.pipeline import generate_candidates
from gcm_pipeline.table import GraspTable

CLUTTER = DATA / "clutter"
_B64 = re.compile(r"data:application/octet-binary;base64,([A-Za-z0-9+/=]+)")


def scene_objects(html: str) -> dict[str, dict]:
    """Path -> {"type", "position" (M, 3), "color" (M, 3), "size"} of each Points object."""
    out = {}
    for m in _B64.findall(html):
        c = umsgpack.unpackb(base64.b64decode(m))
        obj = c.get("object")
        if c.get("type") != "set_object" or obj["object"]["type"] != "Points":
            continue
        attrs = obj["geometries"][0]["data"]["attributes"]
        arrays = {
            k: np.frombuffer(attrs[k]["array"].data, dtype=np.float32).reshape(-1, 3)
            for k in ("position", "color")
        }
        out[c["path"].removeprefix("/meshcat")] = arrays | {"size": obj["materials"][0]["size"]}
    return out


def clutter_cloud() -> tuple[SceneCloud, dict]:
    """The clutter scene's depth image back-projected into the world, with its colours."""
    meta = json.loads((CLUTTER / "scene.json").read_text())
    with np.load(CLUTTER / "scene.npz") as z:
        depth, K, rgb, seg = z["depth"], z["K"], z["rgb"], z["segmap"]
    rows, cols = np.nonzero(depth > 0)
    d = depth[rows, cols].astype(float)
    cam = np.column_stack([(cols - K[0, 2]) * d / K[0, 0], (rows - K[1, 2]) * d / K[1, 1], d])
    pose = Pose(**meta["camera_pose"]).matrix()
    world = cam @ pose[:3, :3].T + pose[:3, 3]
    colors = rgb[rows, cols][:, ::-1]  # BGR in the file
    return SceneCloud(world, colors, seg[rows, cols].astype(np.int64), name="scene"), meta


def clutter_grasps(meta) -> GraspTable:
    cfg = Config.from_dict(
        {
            "candidates": {
                "source": "file",
                "path": str(CLUTTER / "predictions.npz"),
                "format": "contact_graspnet",
                "camera_pose": meta["camera_pose"],
            }
        }
    )
    return generate_candidates(cfg)


def test_the_cloud_and_the_contacts_are_points_objects_of_their_own():
    cloud, meta = clutter_cloud()
    grasps = clutter_grasps(meta)
    # an interpolated row without a contact point adds nothing
    extra = grasps.take(np.array([0])).with_columns(
        contact_x=np.array([np.nan]), origin=np.array(["interpolated"])
    )
    both = GraspTable(
        {k: np.concatenate([np.asarray(grasps[k]), np.asarray(extra[k])]) for k in grasps.columns}
    )
    html, info = render_scene_html(both, None, None, SceneOptions(clouds=(cloud,)))
    objs = scene_objects(html)
    assert "/cloud" in info.paths and "/contacts" in info.paths
    assert {"/cloud", "/contacts"} <= set(SCENE_PATHS)
    drawn = objs["/cloud/scene"]
    assert len(drawn["position"]) == len(cloud.points) == info.cloud_points["scene"] < 10**5
    np.testing.assert_allclose(drawn["position"], cloud.points, atol=1e-6)
    np.testing.assert_allclose(drawn["color"] * 255, cloud.colors, atol=0.01)  # the file's RGB
    contacts = objs["/contacts"]
    assert len(contacts["position"]) == info.contacts == len(grasps) == 150
    expected = np.column_stack([np.asarray(grasps[k]) for k in ("contact_x", "contact_y")])
    np.testing.assert_allclose(contacts["position"][:, :2], expected, atol=1e-6)
    np.testing.assert_array_equal(contacts["color"], np.tile(CONTACT_COLOR, (150, 1)))


def test_a_scene_without_cloud_or_contacts_draws_neither():
    grasps = GraspTable({"dq": np.array([[1.0, 0, 0, 0, 0, 0, 0, 0]])})
    html, info = render_scene_html(grasps, None, None, SceneOptions())
    assert not {"/cloud", "/contacts"} & set(info.paths)
    assert not scene_objects(html) and info.cloud_points == {} and info.contacts == 0


def test_large_clouds_share_the_point_budget_and_keep_their_colours():
    rng = np.random.default_rng(0)
    big = rng.uniform(-1, 1, (150_000, 3))
    small = rng.uniform(-1, 1, (50_000, 3))
    colors = rng.integers(0, 256, (50_000, 3), dtype=np.uint8)
    clouds = (SceneCloud(big, name="big"), SceneCloud(small, colors, name="small"))
    grasps = GraspTable({"dq": np.array([[1.0, 0, 0, 0, 0, 0, 0, 0]])})
    html, info = render_scene_html(grasps, None, None, SceneOptions(clouds=clouds))
    assert info.cloud_points == {"big": 75_000, "small": 25_000}
    assert sum(info.cloud_points.values()) == MAX_CLOUD_POINTS
    assert len(html) < 5_000_000  # 200,000 points give a page under 5 MB
    objs = scene_objects(html)
    # a subset of the cloud's own points, each with its own colour
    pts = objs["/cloud/small"]["position"]
    index = {tuple(p): i for i, p in enumerate(small.astype(np.float32))}
    rows = np.array([index[tuple(p)] for p in pts])
    assert len(np.unique(rows)) == len(rows)
    np.testing.assert_allclose(objs["/cloud/small"]["color"] * 255, colors[rows], atol=0.01)
    # without colours: by height, low and high points far apart in colour
    big_drawn = objs["/cloud/big"]
    z = big_drawn["position"][:, 2]
    low, high = big_drawn["color"][np.argmin(z)], big_drawn["color"][np.argmax(z)]
    assert np.abs(low - high).sum() > 0.5
    # the same subset on every run
    again, _ = render_scene_html(grasps, None, None, SceneOptions(clouds=clouds))
    np.testing.assert_array_equal(
        scene_objects(again)["/cloud/big"]["position"], big_drawn["position"]
    )


def test_a_cloud_with_segments_but_no_colours_is_coloured_by_segment():
    pts = np.array([[0, 0, 0], [0, 0, 1], [1, 0, 0], [1, 0, 1.0]])
    cloud = SceneCloud(pts, segments=np.array([3, 3, 7, 7]))
    grasps = GraspTable({"dq": np.array([[1.0, 0, 0, 0, 0, 0, 0, 0]])})
    html, _ = render_scene_html(grasps, None, None, SceneOptions(clouds=(cloud,)))
    c = scene_objects(html)["/cloud/cloud"]["color"]
    np.testing.assert_array_equal(c[0], c[1])  # one colour per segment, whatever the height
    np.testing.assert_array_equal(c[2], c[3])
    assert np.abs(c[0] - c[2]).sum() > 0.3


def test_a_cloud_of_mismatched_colours_is_refused():
    with pytest.raises(PublishError, match=r"colors has shape \(2, 3\), points has 3 rows"):
        SceneCloud(np.zeros((3, 3)), np.zeros((2, 3), np.uint8))
    with pytest.raises(PublishError, match=r"segments has shape \(4,\)"):
        SceneCloud(np.zeros((3, 3)), segments=np.zeros(4))


def test_the_live_viewer_holds_the_cloud_and_the_contacts():
    from gcm_pipeline.outputs import live
    from gcm_pipeline.outputs.scene import PublishOptions

    cloud, meta = clutter_cloud()
    grasps = clutter_grasps(meta)
    options = PublishOptions(scene=SceneOptions(clouds=(cloud,)))
    viewer = live.open_viewer(grasps, None, None, options)
    try:
        objs = scene_objects(viewer.visualizer.window.get_scene())  # the server's own copy
        assert len(objs["/cloud/scene"]["position"]) == len(cloud.points)
        assert len(objs["/contacts"]["position"]) == viewer.info.contacts == 150
    finally:
        viewer.close()


def test_a_run_with_a_cloud_draws_it_and_its_contacts(tmp_path):
    from helpers import CONFIGS, run_gcm

    from gcm_pipeline.rundir.clouds import read_clouds

    out = tmp_path / "run"
    proc = run_gcm(
        "run", CONFIGS / "clutter_scene.yaml", "--out", out, "--set", "publish.plots=false"
    )
    assert proc.returncode == 0, proc.stderr[-2000:]
    (cloud,) = read_clouds(out / "cloud.npz")
    objs = scene_objects((out / "scene.html").read_text(encoding="utf-8"))
    drawn = objs["/cloud/clutter"]
    assert len(drawn["position"]) == len(cloud.points) > 100
    np.testing.assert_allclose(drawn["position"], cloud.points, atol=1e-6)
    np.testing.assert_allclose(drawn["color"] * 255, cloud.colors, atol=0.01)
    assert objs["/cloud/clutter"]["size"] == cloud.voxel_size
    assert len(objs["/contacts"]["position"]) == 150  # one per candidate, none interpolated
