"""Scene clouds as users hand them over: the layouts other tools write, and what is refused."""

from __future__ import annotations

import numpy as np
import pytest
from PIL import Image

from gcm_pipeline.errors import InputError
from gcm_pipeline.sources.clouds import CloudOptions, read_cloud

K = np.array([[100.0, 0.0, 16.0], [0.0, 100.0, 12.0], [0.0, 0.0, 1.0]])
WHERE = "environment.point_clouds[0]"


def _depth(h=24, w=32, z=0.8):
    return np.full((h, w), z)


def _refused(path, *fragments, **opts):
    with pytest.raises(InputError) as err:
        read_cloud(CloudOptions(path, where=WHERE, **opts))
    msg = str(err.value)
    assert "\n" not in msg and WHERE in msg and str(path) in msg, msg
    for f in fragments:
        assert f in msg, (f, msg)
    return msg


def test_contact_graspnet_inference_output_pc_full_is_a_cloud(tmp_path):
    """Contact-GraspNet's inference keeps ``pc_full`` (N, 3) and ``pc_colors`` (BGR)."""
    pts = np.random.default_rng(0).uniform(0.2, 0.8, (500, 3)).astype(np.float32)
    bgr = np.zeros((500, 3), np.uint8)
    bgr[:, 0] = 200  # blue
    scene = {"pc_full": pts, "pc_colors": bgr, "pred_grasps_cam": {-1.0: np.eye(4)[None]}}
    np.save(tmp_path / "result.npy", scene, allow_pickle=True)
    np.savez(tmp_path / "xyz.npz", xyz=pts)
    cloud = read_cloud(CloudOptions(tmp_path / "result.npy", voxel_size=0.05))
    ref = read_cloud(CloudOptions(tmp_path / "xyz.npz", voxel_size=0.05))
    np.testing.assert_array_equal(cloud.points, ref.points)
    assert cloud.counts["read"] == 500
    assert np.all(cloud.colors == [0, 0, 200])  # shown as RGB


def test_an_npz_without_a_cloud_names_its_members(tmp_path):
    """Contact-GraspNet's predictions file given as the cloud: its keys are listed."""
    np.savez(tmp_path / "p.npz", pred_grasps_cam=np.zeros(1), scores=np.zeros(1))
    _refused(tmp_path / "p.npz", "no cloud in it", "['pred_grasps_cam', 'scores']", "pc_full")


def test_exclude_segments_on_a_cloud_without_segments_is_refused(tmp_path):
    """An exclusion that could never apply (no segmentation) is not silently ignored."""
    np.save(tmp_path / "c.npy", np.random.default_rng(1).uniform(0, 1, (100, 3)))
    _refused(tmp_path / "c.npy", "exclude_segments [3]", "segment ids", exclude_segments=(3,))
    np.savez(tmp_path / "s.npz", depth=_depth(), K=K)
    _refused(tmp_path / "s.npz", "exclude_segments [3]", "segmap", exclude_segments=(3,))


@pytest.mark.parametrize("key", ["intrinsics", "segmap"])
def test_depth_image_keys_on_a_file_of_points_are_refused(tmp_path, key):
    np.save(tmp_path / "c.npy", np.random.default_rng(2).uniform(0, 1, (100, 3)))
    np.save(tmp_path / "seg.npy", np.zeros((24, 32), np.int64))
    value = K if key == "intrinsics" else tmp_path / "seg.npy"
    _refused(tmp_path / "c.npy", f"{WHERE}.{key}", "applies to a depth image", **{key: value})


@pytest.mark.parametrize(
    ("seg", "fragment"),
    [
        (np.full((24, 32), 1.7), "holds 1.7"),
        (np.full((24, 32), np.nan), "holds nan"),
        (np.full((24, 32), 2**63 + 5, np.uint64), "holds 9223372036854775813"),
    ],
)
def test_a_segmentation_of_non_whole_numbers_is_refused(tmp_path, seg, fragment):
    """A float segmap of 1.7 or NaN was cast to some id; the exclusion then missed it."""
    np.save(tmp_path / "seg.npy", seg)
    np.save(tmp_path / "d.npy", _depth())
    _refused(
        tmp_path / "d.npy", fragment, "whole numbers", intrinsics=K, segmap=tmp_path / "seg.npy"
    )


def test_float_and_bool_segmentations_of_whole_numbers_are_read(tmp_path):
    np.save(tmp_path / "d.npy", _depth())
    seg = np.zeros((24, 32))
    seg[:12] = 4.0
    np.save(tmp_path / "seg.npy", seg)
    np.save(tmp_path / "mask.npy", seg > 0)
    a = read_cloud(CloudOptions(tmp_path / "d.npy", intrinsics=K, segmap=tmp_path / "seg.npy"))
    assert set(a.segments.tolist()) == {0, 4}
    b = read_cloud(
        CloudOptions(
            tmp_path / "d.npy", intrinsics=K, segmap=tmp_path / "mask.npy", exclude_segments=(0,)
        )
    )
    assert set(b.segments.tolist()) == {1} and b.counts["excluded_segments"] == 12 * 32


@pytest.mark.parametrize(
    ("arrays", "fragments"),
    [
        ({"rgb": np.zeros((24, 32), np.uint8)}, ["rgb is (24, 32)", "(24, 32, 3)"]),
        ({"rgb": np.zeros((24, 32, 2), np.uint8)}, ["rgb is (24, 32, 2)"]),
        ({"depth": _depth().astype(np.complex128)}, ["dtype complex128", "real numbers"]),
    ],
)
def test_bad_scene_arrays_are_refused_in_one_line(tmp_path, arrays, fragments):
    np.savez(tmp_path / "s.npz", **{"depth": _depth(), "K": K, **arrays})
    _refused(tmp_path / "s.npz", *fragments)


def test_complex_points_are_refused(tmp_path):
    np.save(tmp_path / "c.npy", np.ones((10, 3)) + 1j)
    _refused(tmp_path / "c.npy", "complex128")


def test_an_integer_depth_image_needs_its_depth_scale(tmp_path):
    """A uint16 depth .png in millimetres read as metres lands kilometres away."""
    Image.fromarray(np.full((24, 32), 800, np.uint16)).save(tmp_path / "d.png")
    _refused(tmp_path / "d.png", f"{WHERE}.depth_scale", "0.001", intrinsics=K)
    cloud = read_cloud(CloudOptions(tmp_path / "d.png", intrinsics=K, depth_scale=0.001))
    assert np.allclose(cloud.points[:, 2], 0.805)


HEADER = (
    "VERSION 0.7\nFIELDS x y z\nSIZE {size}\nTYPE {type}\nCOUNT {count}\nPOINTS 1\nDATA ascii\n"
)


@pytest.mark.parametrize(
    ("fields", "fragments"),
    [
        ({"size": "4 4", "type": "F F F", "count": "1 1 1"}, ["SIZE has 2 entries, FIELDS 3"]),
        ({"size": "4 4 4", "type": "F F Q", "count": "1 1 1"}, ["field 'z' has TYPE Q"]),
        ({"size": "4 4 4", "type": "F F F", "count": "1 1 0"}, ["COUNT 0", "COUNT >= 1"]),
    ],
)
def test_a_pcd_with_a_bad_header_is_refused_in_one_line(tmp_path, fields, fragments):
    (tmp_path / "c.pcd").write_text(HEADER.format(**fields) + "1 2 3\n")
    _refused(tmp_path / "c.pcd", "bad PCD header", *fragments)


def test_a_pickled_scene_dict_with_none_for_absent_keys_is_read(tmp_path):
    """``load_available_input_data`` gives ``segmap = None`` when there is none; saved so."""
    np.save(tmp_path / "s.npy", {"depth": _depth(), "K": K, "segmap": None, "rgb": None})
    np.savez(tmp_path / "s.npz", depth=_depth(), K=K)
    a = read_cloud(CloudOptions(tmp_path / "s.npy"))
    np.testing.assert_array_equal(a.points, read_cloud(CloudOptions(tmp_path / "s.npz")).points)
    assert a.segments is None or set(a.segments.tolist()) == {-1}


@pytest.mark.parametrize(
    ("k", "fragments"),
    [
        (None, ["needs intrinsics"]),
        ("abc", ["K has dtype <U3"]),
        ({"fx": 1.0}, ["K has dtype object"]),
    ],
)
def test_a_pickled_scene_dict_with_a_bad_k_is_refused_in_one_line(tmp_path, k, fragments):
    """A K that is not an array crashed with an IndexError."""
    np.save(tmp_path / "s.npy", {"depth": _depth(), "K": k})
    _refused(tmp_path / "s.npy", *fragments)


def test_an_array_that_is_not_n_by_3_says_it_was_taken_for_a_depth_image(tmp_path):
    """An (N, 6) xyz + rgb array is read as a depth image: the message says so and why."""
    np.save(tmp_path / "c.npy", np.ones((100, 6)))
    _refused(tmp_path / "c.npy", "a depth image (100, 6) needs intrinsics", "points are (N, 3)")


def test_the_configs_segmap_overrides_the_npz_segmap(tmp_path):
    """``segmap`` (default: the .npz's) was ignored when the .npz had one."""
    own = np.zeros((24, 32), np.int64)
    given = np.zeros((24, 32), np.int64)
    given[:6] = 7
    np.save(tmp_path / "seg.npy", given)
    np.savez(tmp_path / "s.npz", depth=_depth(), K=K, segmap=own)
    cloud = read_cloud(CloudOptions(tmp_path / "s.npz", segmap=tmp_path / "seg.npy"))
    assert set(cloud.segments.tolist()) == {0, 7}
    assert set(read_cloud(CloudOptions(tmp_path / "s.npz")).segments.tolist()) <= {0, -1}
