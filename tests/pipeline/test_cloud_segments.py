"""The reachability stage's grouping of grasps by their segment (point clouds)."""

from __future__ import annotations

import re

import numpy as np
import pytest
import yaml
from helpers import BOTTLE, QUICK, assert_one_line_error, run_gcm
from pydantic import ValidationError

from gcm_pipeline.config.reach_sections import EnvironmentConfig, PointCloudConfig
from gcm_pipeline.config.sections import Pose
from gcm_pipeline.errors import ConfigError
from gcm_pipeline.pipeline.clouds import (
    cloud_options,
    grasp_segments,
    scene_clouds,
    segment_groups,
    table_merge,
    table_subset,
)
from gcm_pipeline.pipeline.reach import make_checker
from gcm_pipeline.table import GraspTable


def _table():
    # rows 0-3 candidates of segments 5, 5, 8, 8; rows 4-6 interpolated
    return GraspTable(
        {
            "dq": np.tile([1.0, 0, 0, 0, 0, 0, 0, 0], (7, 1)),
            "segment": np.array([5, 5, 8, 8, -1, -1, -1]),
            "vertices": np.array(
                [[-1, -1, -1]] * 4 + [[0, 1, 0], [2, 3, 2], [0, 2, 3]], dtype=np.int64
            ),
        }
    )


def test_interpolated_grasps_take_their_vertices_segment_when_they_share_one():
    np.testing.assert_array_equal(grasp_segments(_table()), [5, 5, 8, 8, 5, 8, -1])


def test_groups_need_a_cloud_that_leaves_the_grasp_segment_out(tmp_path):
    env = EnvironmentConfig(point_clouds=[{"path": tmp_path / "c.npy", "frame": "world"}])
    groups = segment_groups(_table(), env)
    assert [(s, r.tolist()) for s, r in groups] == [(None, [6]), (5, [0, 1, 4]), (8, [2, 3, 5])]
    off = EnvironmentConfig(
        point_clouds=[
            {"path": tmp_path / "c.npy", "frame": "world", "exclude_grasp_segment": False}
        ]
    )
    assert segment_groups(_table(), off) is None
    assert segment_groups(_table(), EnvironmentConfig()) is None


def test_subsets_renumber_vertices_and_merge_back_in_row_order():
    table = _table()
    rows = np.array([2, 3, 5])
    sub = table_subset(table, rows)
    np.testing.assert_array_equal(sub["vertices"][2], [0, 1, 0])
    parts = [
        (r, table_subset(table, r).with_columns(reason=np.array([f"r{i}" for i in r])))
        for r in (np.array([0, 1, 4, 6]), rows)
    ]
    merged = table_merge(table, parts)
    assert merged["reason"].tolist() == [f"r{i}" for i in range(7)]
    np.testing.assert_array_equal(merged["vertices"], table["vertices"])


def test_cloud_keys_are_checked_with_the_config(tmp_path):

    path = tmp_path / "c.npy"
    for bad, words in [
        ({"frame": "world", "camera_pose": {"xyz": [0, 0, 1]}}, "applies to frame 'camera'"),
        ({"frame": "world", "max_depth": 1.0}, "max_depth"),
        ({"crop_min": [0, 0, 1], "crop_max": [1, 1, 0]}, "exceeds crop_max"),
        ({"voxel_size": 0.0005}, "greater than or equal to 0.001"),
        ({"intrinsics": [[1, 0, 0], [0, 1, 0]]}, "intrinsics"),
        ({"voxel": 0.01}, "voxel"),
    ]:
        with pytest.raises(ValidationError, match=words):
            PointCloudConfig(path=path, **bad)


def test_a_camera_cloud_takes_the_candidates_camera_pose(tmp_path):

    pc = PointCloudConfig(path=tmp_path / "c.npy")
    with pytest.raises(ConfigError, match=r"environment.point_clouds\[2\]: frame 'camera' needs"):
        cloud_options(2, pc, None, None)
    cam = Pose(xyz=(0.5, 0.0, 0.8), rpy_deg=(180.0, 0.0, 0.0))
    np.testing.assert_array_equal(cloud_options(0, pc, None, cam).camera_pose, cam.matrix())
    own = PointCloudConfig(path=tmp_path / "c.npy", camera_pose={"xyz": [1, 2, 3]})
    assert cloud_options(0, own, None, cam).camera_pose[:3, 3].tolist() == [1, 2, 3]
    near = PointCloudConfig(path=tmp_path / "c.npy", frame="world", exclude_object_distance=0.01)
    with pytest.raises(ConfigError, match="exclude_object_distance needs an 'object'"):
        cloud_options(0, near, None, None)


def test_a_cloud_around_the_base_is_one_warning_naming_its_config_key(panda, tmp_path, caplog):
    """The cloud's tiles all overlap the base: one warning, naming the cloud, not each tile."""
    pts = np.random.default_rng(0).uniform([-0.1, -0.1, 0.0], [0.1, 0.1, 0.3], (5000, 3))
    np.save(tmp_path / "c.npy", pts)
    env = EnvironmentConfig(
        table=None, point_clouds=[{"path": tmp_path / "c.npy", "frame": "world", "name": "shelf"}]
    )
    with caplog.at_level("WARNING"):
        checker = make_checker(panda, env, None)
    tiles = {shape for _, shape in checker.static_collisions}
    assert len(tiles) > 1  # the tiles shelf_0, shelf_1, ... collide on their own
    lines = [r.getMessage() for r in caplog.records if "overlaps the robot" in r.getMessage()]
    assert len(lines) == 1, lines
    assert lines[0].startswith("environment.point_clouds[0] (shelf) overlaps the robot's fixed")
    assert "crop_min/crop_max" in lines[0]


_BALL = {"shape": "sphere", "dims": {"radius": 0.01}, "pose": {"xyz": [2.0, 2.0, 2.0]}}


@pytest.mark.parametrize(
    ("env", "fragment"),
    [
        (
            {"point_clouds": [{"path": "a.npy", "name": "s"}, {"path": "b.npy", "name": "s"}]},
            "point_clouds[1]: name 's' is taken by point_clouds[0]",
        ),
        (
            {"obstacles": [_BALL, {**_BALL, "name": "obstacle_0"}]},
            "obstacles[1]: name 'obstacle_0' is taken by obstacles[0]",
        ),
        (
            {"obstacles": [_BALL], "point_clouds": [{"path": "a.npy", "name": "obstacle"}]},
            "name 'obstacle_0' is the name of a tile of point_clouds[0]",
        ),
        ({"obstacles": [{**_BALL, "name": "table"}]}, "name 'table' is taken by the table"),
    ],
)
def test_world_shapes_with_the_same_name_are_refused(env, fragment):
    """Two shapes of one name crashed the collision checker (it finds shapes by name)."""
    with pytest.raises(ValidationError, match=re.escape(fragment)):
        EnvironmentConfig.model_validate(env)


def test_two_clouds_of_one_name_stop_the_run_in_one_line(tmp_path):
    np.save(tmp_path / "c.npy", np.random.default_rng(0).uniform(0.4, 0.6, (100, 3)))
    cfg = yaml.safe_load(BOTTLE.read_text())
    cloud = {"path": "c.npy", "frame": "world", "name": "s"}
    cfg["environment"] = {"point_clouds": [cloud, cloud]}
    cfg["output"] = {"dir": "out"}
    (tmp_path / "run.yaml").write_text(yaml.safe_dump(cfg))
    res = run_gcm("run", tmp_path / "run.yaml", "-q", *QUICK)
    assert_one_line_error(res.returncode, res.stderr, "point_clouds[1]", "'s'")
    assert not (tmp_path / "out").exists()


def test_exclude_segments_that_match_no_point_are_a_warning(tmp_path, caplog):
    """A typo in exclude_segments would leave the target's points in as an obstacle."""
    seg = np.zeros((24, 32), np.int64)
    seg[:6] = 4
    k = [[100.0, 0.0, 16.0], [0.0, 100.0, 12.0], [0.0, 0.0, 1.0]]
    np.savez(tmp_path / "s.npz", depth=np.full((24, 32), 0.8), K=np.array(k), segmap=seg)
    cloud = {"path": tmp_path / "s.npz", "camera_pose": {"xyz": [0.0, 0.0, 1.0]}}
    with caplog.at_level("WARNING"):
        scene_clouds(EnvironmentConfig(point_clouds=[{**cloud, "exclude_segments": [4]}]))
        assert "matched no point" not in caplog.text
        scene_clouds(EnvironmentConfig(point_clouds=[{**cloud, "exclude_segments": [5]}]))
    assert "point_clouds[0].exclude_segments [5] matched no point" in caplog.text
    assert "(its segment ids: [0, 4])" in caplog.text
