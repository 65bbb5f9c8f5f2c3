"""Scene clouds read from files: formats, voxelisation, exclusions, bounded memory, bad input."""

from __future__ import annotations

import tracemalloc

import numpy as np
import pytest
import trimesh
import yaml
from helpers import BOTTLE, QUICK, assert_one_line_error, run_gcm
from PIL import Image

from gcm_pipeline.errors import InputError
from gcm_pipeline.geometry.clouds import VoxelGrid
from gcm_pipeline.rundir.clouds import read_clouds, write_clouds
from gcm_pipeline.sources import clouds as source
from gcm_pipeline.sources.clouds import CloudOptions, read_cloud
from gcm_pipeline.sources.files import cloud_formats

K = [[100.0, 0.0, 16.0], [0.0, 100.0, 12.0], [0.0, 0.0, 1.0]]


def _depth(h=24, w=32, z=0.8):
    return np.full((h, w), z)


def _cells(points, size):
    return {tuple(k) for k in np.floor(np.asarray(points) * (1.0 / size)).astype(int).tolist()}


def test_points_are_voxelised_on_the_world_grid_and_nan_counted(tmp_path):
    rng = np.random.default_rng(0)
    pts = rng.uniform(-0.3, 0.3, (5000, 3))
    pts[:7] = np.nan
    pts[7:10, 1] = np.inf
    np.save(tmp_path / "c.npy", pts)
    cloud = read_cloud(CloudOptions(tmp_path / "c.npy", voxel_size=0.05))
    assert cloud.counts["read"] == 5000 and cloud.counts["non_finite"] == 10
    assert cloud.counts["kept"] == 4990
    assert _cells(cloud.points, 0.05) == _cells(pts[10:], 0.05)
    assert len(cloud) == cloud.counts["voxels"] == len(_cells(pts[10:], 0.05))


def test_a_depth_image_becomes_points_as_contact_graspnet_does(tmp_path):
    """``depth2pc``: x = (u - cx) z / fx, y = (v - cy) z / fy; depth <= 0 is no point."""
    depth = _depth()
    depth[3, 4] = 0.0
    depth[5, 6] = np.nan
    np.savez(tmp_path / "s.npz", depth=depth, K=np.array(K))
    pose = np.eye(4)
    pose[:3, 3] = (1.0, 2.0, 3.0)
    cloud = read_cloud(CloudOptions(tmp_path / "s.npz", voxel_size=0.001, camera_pose=pose))
    v, u = np.nonzero(depth > 0)
    z = depth[v, u]
    want = np.stack([(u - 16.0) * z / 100.0, (v - 12.0) * z / 100.0, z], 1) + (1.0, 2.0, 3.0)
    assert _cells(cloud.points, 0.001) == _cells(want, 0.001)
    c = cloud.counts
    assert (c["read"], c["no_depth"], c["non_finite"]) == (24 * 32, 1, 1)


def test_contact_graspnet_layouts_read_alike(tmp_path):
    """The .npz keys, the pickled .npy dict, xyz + xyz_color; rgb is stored BGR."""
    depth = _depth()
    seg = np.zeros(depth.shape, np.int64)
    seg[:10] = 4
    bgr = np.zeros((*depth.shape, 3), np.uint8)
    bgr[..., 0] = 255
    np.savez(tmp_path / "s.npz", depth=depth, K=np.array(K), segmap=seg, rgb=bgr)
    np.save(tmp_path / "s.npy", {"depth": depth, "K": np.array(K), "segmap": seg})
    a = read_cloud(CloudOptions(tmp_path / "s.npz", voxel_size=0.01))
    b = read_cloud(CloudOptions(tmp_path / "s.npy", voxel_size=0.01))
    np.testing.assert_array_equal(a.points, b.points)
    np.testing.assert_array_equal(a.segments, b.segments)
    assert set(a.segments.tolist()) == {0, 4}
    np.testing.assert_array_equal(a.colors[0], [0, 0, 255])
    xyz = np.random.default_rng(1).uniform(0, 1, (300, 3))
    np.savez(tmp_path / "x.npz", xyz=xyz, xyz_color=np.full((300, 3), 9, np.uint8))
    x = read_cloud(CloudOptions(tmp_path / "x.npz", voxel_size=0.1))
    assert _cells(x.points, 0.1) == _cells(xyz, 0.1) and np.all(x.colors == 9)


def test_ply_and_pcd_read_the_same_points(tmp_path):
    pts = np.random.default_rng(2).uniform(-1, 1, (400, 3)).astype(np.float32)
    trimesh.PointCloud(pts).export(tmp_path / "c.ply")
    head = (
        "# .PCD v0.7\nVERSION 0.7\nFIELDS x y z rgb\nSIZE 4 4 4 4\nTYPE F F F U\n"
        "COUNT 1 1 1 1\nWIDTH 400\nHEIGHT 1\nVIEWPOINT 0 0 0 1 0 0 0\nPOINTS 400\nDATA {}\n"
    )
    rgb = np.full(400, (10 << 16) | (20 << 8) | 30, np.uint32)
    rec = np.zeros(400, [("x", "f4"), ("y", "f4"), ("z", "f4"), ("rgb", "u4")])
    rec["x"], rec["y"], rec["z"], rec["rgb"] = pts[:, 0], pts[:, 1], pts[:, 2], rgb
    (tmp_path / "b.pcd").write_bytes(head.format("binary").encode() + rec.tobytes())
    rows = "\n".join(
        f"{x!r} {y!r} {z!r} {c}" for (x, y, z), c in zip(pts.tolist(), rgb, strict=True)
    )
    (tmp_path / "a.pcd").write_text(head.format("ascii") + rows + "\n")
    want = _cells(pts.astype(np.float64), 0.05)
    for name in ("c.ply", "a.pcd", "b.pcd"):
        cloud = read_cloud(CloudOptions(tmp_path / name, voxel_size=0.05))
        assert _cells(cloud.points, 0.05) == want, name
    np.testing.assert_array_equal(cloud.colors[0], [10, 20, 30])


def test_crop_max_depth_segments_and_object_exclusion_are_counted(tmp_path):
    depth = _depth()
    depth[:, :4] = 2.0
    seg = np.zeros(depth.shape, np.int64)
    seg[:4] = 7
    np.savez(tmp_path / "s.npz", depth=depth, K=np.array(K), segmap=seg)
    cloud = read_cloud(
        CloudOptions(
            tmp_path / "s.npz",
            max_depth=1.0,
            crop=(np.array([-1.0, -1.0, 0.0]), np.array([1.0, 0.05, 1.0])),
            exclude_segments=(7,),
            exclude=lambda p: p[:, 0] > 0.1,
        )
    )
    c = cloud.counts
    assert c["beyond_max_depth"] == 24 * 4
    assert c["outside_crop"] > 0 and c["excluded_segments"] > 0 and c["excluded_object"] > 0
    assert np.all(cloud.points[:, 0] <= 0.1 + 0.005) and np.all(cloud.points[:, 1] <= 0.055)
    kept = c["read"] - sum(c[k] for k in c if k not in ("read", "kept", "voxels"))
    assert kept == c["kept"]


def test_cloud_npz_round_trips(tmp_path):
    grid = VoxelGrid(0.02)
    grid.add(np.random.default_rng(3).uniform(0, 1, (500, 3)), np.arange(500) % 3)
    cloud = grid.cloud(counts={}, name="shelf", source="x")
    write_clouds([cloud], tmp_path / "cloud.npz")
    (back,) = read_clouds(tmp_path / "cloud.npz")
    assert back.name == "shelf" and back.colors is None
    np.testing.assert_array_equal(back.points, cloud.points)
    np.testing.assert_array_equal(back.segments, cloud.segments)


def test_a_large_cloud_is_read_in_chunks_with_bounded_memory(tmp_path, monkeypatch):
    """Memory follows the chunk and the voxels, not the points (2e6 points: 48 MB on disk)."""
    n = 2_000_000
    pts = np.random.default_rng(4).uniform(0, 1, (n, 3))
    np.save(tmp_path / "big.npy", pts)
    del pts
    monkeypatch.setattr(source, "CLOUD_CHUNK", 1 << 16)
    tracemalloc.start()
    try:
        cloud = read_cloud(CloudOptions(tmp_path / "big.npy", voxel_size=0.1))
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert cloud.counts["read"] == n and len(cloud) == 1000
    assert peak < 16e6, peak  # the points alone take 48 MB


@pytest.mark.parametrize(
    ("make", "fragments"),
    [
        (lambda d: np.save(d / "c.npy", np.zeros((0, 3))), ["no point is left"]),
        (lambda d: np.save(d / "c.npy", np.full((5, 3), np.nan)), ["no point", "non_finite 5"]),
        (lambda d: np.save(d / "c.npy", _depth()), ["needs intrinsics"]),
        (
            lambda d: np.savez(d / "c.npz", depth=_depth(), K=np.eye(2)),
            ["K must be 3 x 3", "(2, 2)"],
        ),
        (
            lambda d: np.savez(d / "c.npz", depth=_depth(), K=np.array(K), segmap=np.zeros((5, 5))),
            ["segmentation is (5, 5)", "(24, 32)"],
        ),
        (lambda d: np.savez(d / "c.npz", points=np.zeros((3, 3))), ["'depth' + 'K'", "xyz"]),
        (lambda d: np.save(d / "c.npy", np.array([[5000.0, 0, 0]])), ["from the world origin"]),
        (
            lambda d: (d / "c.pcd").write_text(
                "FIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nPOINTS 1\nDATA binary_compressed\n"
            ),
            ["binary_compressed"],
        ),
        (lambda d: (d / "c.xyz").write_text("0 0 0\n"), ["unknown cloud format", ".xyz"]),
    ],
)
def test_bad_clouds_are_refused_in_one_line(tmp_path, make, fragments):
    make(tmp_path)
    (path,) = list(tmp_path.iterdir())
    with pytest.raises(InputError) as err:
        read_cloud(CloudOptions(path, where="environment.point_clouds[0]"))
    msg = str(err.value)
    assert "\n" not in msg and "environment.point_clouds[0]" in msg and str(path) in msg
    for f in fragments:
        assert f in msg, (f, msg)


def test_too_many_voxels_and_too_large_whole_files_are_refused(tmp_path, monkeypatch):
    grid = VoxelGrid(0.01, max_voxels=100, where="environment.point_clouds[0]")
    with pytest.raises(InputError, match="more than 100 occupied voxels.*MAX_CLOUD_VOXELS"):
        grid.add(np.random.default_rng(5).uniform(0, 1, (5000, 3)))
        grid.cloud(counts={}, name="c", source="")
    trimesh.PointCloud(np.zeros((10, 3))).export(tmp_path / "c.ply")
    monkeypatch.setattr(cloud_formats, "MAX_CLOUD_FILE_BYTES", 10)
    with pytest.raises(InputError, match="MAX_CLOUD_FILE_BYTES"):
        read_cloud(CloudOptions(tmp_path / "c.ply"))


def test_a_bad_cloud_stops_the_run_before_anything_is_written(tmp_path):
    np.save(tmp_path / "c.npy", _depth())
    cfg = yaml.safe_load(BOTTLE.read_text())
    cfg["environment"] = {"point_clouds": [{"path": "c.npy", "frame": "world"}]}
    cfg["output"] = {"dir": "out"}
    (tmp_path / "run.yaml").write_text(yaml.safe_dump(cfg))
    res = run_gcm("run", tmp_path / "run.yaml", "-q", *QUICK)
    assert_one_line_error(res.returncode, res.stderr, "environment.point_clouds[0]", "intrinsics")
    assert not (tmp_path / "out").exists()


def test_a_png_depth_image_in_millimetres_with_a_label_png(tmp_path):
    """GraspNet-1Billion's layout: depth/0000.png (uint16 mm), label/0000.png, camK.npy."""
    depth_mm = np.full((24, 32), 800, np.uint16)
    depth_mm[0, 0] = 0
    label = np.zeros((24, 32), np.uint8)
    label[:6] = 3
    Image.fromarray(depth_mm).save(tmp_path / "depth.png")
    Image.fromarray(label).save(tmp_path / "label.png")
    np.savez(tmp_path / "s.npz", depth=depth_mm / 1000.0, K=np.array(K), segmap=label)
    png = read_cloud(
        CloudOptions(
            tmp_path / "depth.png",
            intrinsics=np.array(K),
            depth_scale=0.001,
            segmap=tmp_path / "label.png",
        )
    )
    ref = read_cloud(CloudOptions(tmp_path / "s.npz"))
    np.testing.assert_allclose(png.points, ref.points)
    np.testing.assert_array_equal(png.segments, ref.segments)
    assert png.counts["no_depth"] == 1
    with pytest.raises(InputError, match="needs intrinsics"):
        read_cloud(CloudOptions(tmp_path / "depth.png", where="environment.point_clouds[0]"))
