"""The object a grasp file names: its mesh found under a root, stood on the table, grasps along."""

from __future__ import annotations

import math
import shutil
from pathlib import Path

import numpy as np
import pytest
import trimesh
import yaml
from helpers import DATA

from gcm_pipeline.config.run import Config
from gcm_pipeline.errors import InputError
from gcm_pipeline.pipeline import candidate_poses, place_file_object
from gcm_pipeline.sources.file_object import find_mesh, load_scaled, stable_placement

h5py = pytest.importorskip("h5py")

ACRONYM = DATA / "acronym"
MUG_H5 = ACRONYM / "Mug_10f6e09036350e92b3f21f1137c3c347_0.0002682457830986903.h5"
MUG_OBJ = ACRONYM / "10f6e09036350e92b3f21f1137c3c347.obj"
MUG_SCALE = 0.0002682457830986903
MUG_NAME = "meshes/Mug/10f6e09036350e92b3f21f1137c3c347.obj"


def _config(path: Path, **candidates) -> Config:
    return Config.from_dict(
        {
            "candidates": {"source": "file", "path": str(path), "format": "acronym", **candidates},
            "publish": {"html": False, "plots": False},
        }
    )


def _world_mesh(cfg: Config) -> trimesh.Trimesh:
    obj = cfg.object
    assert obj is not None and obj.shape == "mesh"
    mesh = trimesh.load(str(obj.mesh), force="mesh")
    mesh.apply_scale(obj.scale)
    mesh.apply_transform(obj.pose.matrix())
    return mesh


def test_the_mug_stands_upright_on_the_table_at_x_y():
    """The issue's hand work, done from the file: the mug's z offset was found to be -0.0514."""
    cfg = place_file_object(_config(MUG_H5, placement={"xy": [0.45, -0.2]}))
    obj = cfg.object
    assert obj is not None and Path(obj.mesh) == MUG_OBJ
    assert obj.scale == pytest.approx(MUG_SCALE)
    assert cfg.candidates.frame == "object"
    pose = obj.pose.matrix()
    assert pose[2, 2] == pytest.approx(1.0, abs=1e-6)  # upright: the mesh's z stays up
    assert pose[2, 3] == pytest.approx(-0.0514, abs=5e-4)
    lo, hi = _world_mesh(cfg).bounds
    assert lo[2] == pytest.approx(0.0, abs=1e-9)  # lowest point on the table top (z = 0)
    assert ((lo[:2] + hi[:2]) / 2) == pytest.approx([0.45, -0.2], abs=1e-9)
    assert hi[2] - lo[2] == pytest.approx(0.101, abs=0.002)  # a 10 cm mug, standing


def test_yaw_turns_the_mug_about_its_footprint_centre_on_a_raised_table():
    base = place_file_object(_config(MUG_H5, placement={"xy": [0.5, 0.1]}))
    cfg = Config.from_dict(
        {
            **_config(MUG_H5, placement={"xy": [0.5, 0.1], "yaw_deg": 90.0}).to_dict(),
            "environment": {"table": {"height": 0.2}},
        }
    )
    turned = place_file_object(cfg)
    a, b = base.object.pose.matrix(), turned.object.pose.matrix()
    rz = np.array([[0.0, -1, 0], [1, 0, 0], [0, 0, 1]])
    assert b[:3, :3] == pytest.approx(rz @ a[:3, :3], abs=1e-9)
    centre = np.array([0.5, 0.1])  # the footprint centre: the point yaw turns about
    assert b[:2, 3] - centre == pytest.approx(rz[:2, :2] @ (a[:2, 3] - centre), abs=1e-9)
    assert b[2, 3] - a[2, 3] == pytest.approx(0.2, abs=1e-9)
    assert _world_mesh(turned).bounds[0, 2] == pytest.approx(0.2, abs=1e-9)


def test_grasps_move_with_the_placed_mug():
    """Each grasp keeps its place on the mug: same distance to the surface, same local pose."""
    raw = _config(MUG_H5, success_only=True, limit=40)
    cfg = place_file_object(raw)
    world, _ = candidate_poses(cfg)
    in_mesh, _ = candidate_poses(
        Config.from_dict(
            {
                "object": {"shape": "mesh", "mesh": str(MUG_OBJ), "scale": MUG_SCALE},
                "candidates": {**raw.candidates.model_dump(), "frame": "object"},
            }
        )
    )
    pose = cfg.object.pose.matrix()
    assert world == pytest.approx(pose @ in_mesh, abs=1e-9)
    local = trimesh.load(str(MUG_OBJ), force="mesh")
    local.apply_scale(MUG_SCALE)
    d_local = trimesh.proximity.closest_point(local, in_mesh[:, :3, 3])[1]
    d_world = trimesh.proximity.closest_point(_world_mesh(cfg), world[:, :3, 3])[1]
    assert d_world == pytest.approx(d_local, abs=1e-6)  # rpy round trip: ~1e-8 m
    assert d_world.max() < 0.03  # the grasp centres lie at the mug, not 0.5 m away


def test_stable_pose_index_picks_by_probability_and_says_when_out_of_range():
    mesh = load_scaled(MUG_OBJ, MUG_SCALE, "mug")
    first = stable_placement(mesh, (0.0, 0.0), 0.0, 0.0, 0, "mug")
    assert first.index == 0 and first.count > 2 and 0 < first.probability <= 1
    lying = mesh.copy().apply_transform(first.pose)
    assert lying.bounds[0, 2] == pytest.approx(0.0, abs=1e-9)
    assert abs(first.pose[2, 2]) < 0.1  # the most probable pose lays the mug on its side
    upright = stable_placement(mesh, (0.0, 0.0), 0.0, 0.0, None, "mug")
    assert upright.probability < first.probability and upright.pose[2, 2] > 0.999
    with pytest.raises(InputError, match=r"candidates\.placement\.stable_pose: 99 is out of") as e:
        stable_placement(mesh, (0.0, 0.0), 0.0, 0.0, 99, "mug")
    assert e.value.key == "candidates.placement.stable_pose"


def _far_origin_box(path: Path) -> None:
    """A 0.2 x 0.1 x 0.05 m box whose geometry lies 2.7 m from its mesh origin."""
    box = trimesh.creation.box(extents=(0.2, 0.1, 0.05))
    box.apply_translation((2.7, 1.2, 0.3))
    path.parent.mkdir(parents=True, exist_ok=True)
    box.export(path)


def _h5(path: Path, name: str, scale: float = 1.0, n: int = 3) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    with h5py.File(path, "w") as f:
        t = np.tile(np.eye(4), (n, 1, 1))
        t[:, :3, 3] = (2.7, 1.2, 0.4)
        f["grasps/transforms"] = t
        f["grasps/qualities/flex/object_in_gripper"] = np.ones(n)
        f["object/file"] = name
        f["object/scale"] = scale
    return path


def test_a_mesh_origin_far_from_its_geometry_is_placed_by_the_geometry(tmp_path):
    """ACRONYM's table mesh has its origin 2.7 m from its geometry: x, y place the geometry."""
    _far_origin_box(tmp_path / "data" / "meshes" / "Box" / "b.obj")
    h5 = _h5(tmp_path / "data" / "grasps" / "Box_b.h5", "meshes/Box/b.obj")
    cfg = place_file_object(_config(h5, placement={"xy": [0.6, -0.1]}))
    lo, hi = _world_mesh(cfg).bounds
    assert ((lo[:2] + hi[:2]) / 2) == pytest.approx([0.6, -0.1], abs=1e-9)
    assert lo[2] == pytest.approx(0.0, abs=1e-9) and hi[2] == pytest.approx(0.05, abs=1e-9)
    world, _ = candidate_poses(cfg)  # the grasps, 0.1 m above the box's centre, follow it
    assert world[:, :3, 3].mean(axis=0)[:2] == pytest.approx([0.6, -0.1], abs=1e-6)


def test_mesh_resolution_against_the_root(tmp_path):
    # ACRONYM's layout: <root>/grasps/x.h5 beside <root>/meshes/...
    layout = tmp_path / "acronym"
    (layout / "meshes" / "Mug").mkdir(parents=True)
    shutil.copy(MUG_OBJ, layout / MUG_NAME)
    h5 = _h5(layout / "grasps" / "Mug.h5", MUG_NAME)
    assert find_mesh(h5, MUG_NAME, "acronym", None) == layout / MUG_NAME
    # the mesh beside the grasp file (as tests/data/acronym ships it)
    assert find_mesh(MUG_H5, MUG_NAME, "acronym", None) == MUG_OBJ
    # a stated root
    other = tmp_path / "elsewhere"
    h5b = _h5(other / "Mug.h5", MUG_NAME)
    assert find_mesh(h5b, MUG_NAME, "acronym", layout) == layout / MUG_NAME
    cfg = place_file_object(_config(h5b, mesh_root=str(layout)))
    assert Path(cfg.object.mesh) == layout / MUG_NAME
    with pytest.raises(InputError) as e:
        find_mesh(h5b, MUG_NAME, "acronym", None)
    msg = str(e.value)
    for tried in (
        tmp_path / MUG_NAME,
        other / MUG_NAME,
        other / "10f6e09036350e92b3f21f1137c3c347.obj",
    ):
        assert str(tried) in msg
    assert "object/file" in msg and "candidates.mesh_root" in msg and str(h5b) in msg
    assert e.value.key == "candidates.mesh_root"


def test_an_explicit_object_or_world_frame_keeps_the_config():
    explicit = Config.from_dict(
        {
            "object": {"shape": "cylinder", "dims": {"radius": 0.04, "height": 0.1}},
            "candidates": {"source": "file", "path": str(MUG_H5), "frame": "object"},
        }
    )
    assert place_file_object(explicit) is explicit
    world = _config(MUG_H5, frame="world")
    assert place_file_object(world) is world
    npy = Config.from_dict({"candidates": {"source": "file", "path": str(DATA / "x.npy")}})
    assert place_file_object(npy) is npy  # a format that names no mesh: no file read


def test_placement_keys_are_validated():
    from gcm_pipeline.errors import ConfigError

    for bad in ({"stable_pose": -1}, {"stable_pose": "lying"}, {"xy": [0.1]}, {"yaw_deg": "x"}):
        with pytest.raises(ConfigError, match="candidates.placement"):
            _config(MUG_H5, placement=bad)
    assert math.isclose(_config(MUG_H5).candidates.placement.xy[0], 0.5)


def test_the_scene_frames_the_placed_mesh_by_its_geometry_not_its_origin(tmp_path):
    from gcm_pipeline.outputs.scene_shapes import object_points
    from gcm_pipeline.pipeline.outputs import scene_shape

    _far_origin_box(tmp_path / "meshes" / "Box" / "b.obj")
    h5 = _h5(tmp_path / "grasps" / "Box_b.h5", "meshes/Box/b.obj")
    cfg = place_file_object(_config(h5))
    pts = object_points(scene_shape(cfg.object))
    lo, hi = _world_mesh(cfg).bounds
    assert pts.min(axis=0) == pytest.approx(lo, abs=1e-9)
    assert pts.max(axis=0) == pytest.approx(hi, abs=1e-9)
    assert np.linalg.norm(cfg.object.pose.matrix()[:2, 3]) > 2.0  # the origin, far away


def test_a_graspgen_file_names_its_mesh_too(tmp_path):
    (tmp_path / "objects").mkdir()
    shutil.copy(MUG_OBJ, tmp_path / "objects" / "mug.obj")
    t = np.eye(4)
    t[:3, 3] = (0.0, 0.0, 0.15)
    path = tmp_path / "grasps" / "mug.yaml"
    path.parent.mkdir()
    path.write_text(
        yaml.safe_dump(
            {
                "object": {"file": "objects/mug.obj", "scale": MUG_SCALE},
                "gripper": {"name": "franka_panda"},
                "grasps": {"transforms": [t.tolist()], "object_in_gripper": [1]},
            }
        )
    )
    cfg = place_file_object(_config(path, format="graspgen"))
    assert Path(cfg.object.mesh) == tmp_path / "objects" / "mug.obj"
    assert cfg.object.scale == pytest.approx(MUG_SCALE)
    assert _world_mesh(cfg).bounds[0, 2] == pytest.approx(0.0, abs=1e-9)
    path.write_text(path.read_text().replace(f"scale: {MUG_SCALE}", "scale: -2.0"))
    with pytest.raises(InputError, match=r"object\.scale must be a positive number, got -2\.0"):
        place_file_object(_config(path, format="graspgen"))
