"""The reachability stage's grouping of grasps by their segment (point clouds)."""

from __future__ import annotations

import numpy as np

from gcm_pipeline.config.reach_sections import EnvironmentConfig
from gcm_pipeline.pipeline.clouds import grasp_segments, segment_groups, table_merge, table_subset
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
