"""``gcm`` on a grasp file naming its object: found, placed, warned about, or one-line errors."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest
import yaml
from helpers import DATA, QUICK, assert_one_line_error

h5py = pytest.importorskip("h5py")
trimesh = pytest.importorskip("trimesh")

MUG_OBJ = DATA / "acronym" / "10f6e09036350e92b3f21f1137c3c347.obj"


def _grasp_file(folder: Path, name: str = "meshes/Box/x.obj", scale: float = 1.0) -> Path:
    """An ACRONYM file of 3 grasps from above, 0.1 m over the mesh origin."""
    folder.mkdir(parents=True, exist_ok=True)
    path = folder / "grasps.h5"
    t = np.tile(np.eye(4), (3, 1, 1))
    t[:, :3, :3] = np.diag([1.0, -1.0, -1.0])
    t[:, 0, 3] = [-0.01, 0.0, 0.01]
    t[:, 1, 3] = [0.0, 0.01, 0.0]
    t[:, 2, 3] = 0.2
    with h5py.File(path, "w") as f:
        f["grasps/transforms"] = t
        f["grasps/qualities/flex/object_in_gripper"] = np.ones(3)
        f["object/file"] = name
        f["object/scale"] = scale
    return path


def _config(tmp_path: Path, grasps: Path, **candidates) -> Path:
    cfg = tmp_path / "cfg.yaml"
    cfg.write_text(
        yaml.safe_dump(
            {
                "candidates": {
                    "source": "file",
                    "path": str(grasps),
                    "format": "acronym",
                    **candidates,
                }
            }
        )
    )
    return cfg


def test_validate_places_the_named_mesh_on_the_table(cli, tmp_path):
    grasps = _grasp_file(tmp_path / "data" / "grasps")
    (tmp_path / "data" / "meshes" / "Box").mkdir(parents=True)
    box = trimesh.creation.box(extents=(0.05, 0.05, 0.1))
    box.export(tmp_path / "data" / "meshes" / "Box" / "x.obj")
    cfg = _config(tmp_path, grasps, placement={"xy": [0.4, 0.1]})
    code, text, err = cli("validate", cfg)
    assert code == 0, err
    assert "#   object      mesh at [0.4, 0.1, 0.05]" in text  # the box's centre 5 cm up
    resolved = yaml.safe_load(
        text.split("# resolved config (defaults filled in, paths absolute):")[1]
    )
    assert resolved["object"]["mesh"] == str(tmp_path / "data" / "meshes" / "Box" / "x.obj")
    assert resolved["candidates"]["frame"] == "object"
    assert "watertight" not in err


def test_a_missing_mesh_is_one_line_naming_file_key_and_every_path_tried(cli, tmp_path):
    out = tmp_path / "results" / "run"
    grasps = _grasp_file(tmp_path / "data" / "grasps")
    code, _, err = cli("run", _config(tmp_path, grasps), "--out", out)
    assert_one_line_error(
        code,
        err,
        str(grasps),
        "object/file 'meshes/Box/x.obj': mesh not found",
        "candidates.mesh_root",
        str(tmp_path / "data" / "meshes" / "Box" / "x.obj"),
        str(tmp_path / "data" / "grasps" / "meshes" / "Box" / "x.obj"),
        str(tmp_path / "data" / "grasps" / "x.obj"),
    )
    assert not out.parent.exists()  # nothing written
    code, _, err = cli("validate", _config(tmp_path, grasps, mesh_root=str(tmp_path / "nowhere")))
    assert_one_line_error(
        code, err, "under candidates.mesh_root", str(tmp_path / "nowhere" / "meshes" / "Box")
    )


@pytest.mark.parametrize("scale", [-1.0, 0.0, float("nan"), float("inf")])
def test_a_bad_scale_is_one_line_naming_file_and_key(cli, tmp_path, scale):
    grasps = _grasp_file(tmp_path / "g", scale=scale)
    shutil.copy(MUG_OBJ, tmp_path / "g" / "x.obj")
    code, _, err = cli("validate", _config(tmp_path, grasps))
    assert_one_line_error(code, err, str(grasps), "object/scale must be a positive number")


def test_an_unreadable_mesh_is_one_line_naming_it(cli, tmp_path):
    grasps = _grasp_file(tmp_path / "g")
    (tmp_path / "g" / "x.obj").write_text("this is not a mesh\n")
    code, _, err = cli("validate", _config(tmp_path, grasps))
    assert_one_line_error(code, err, str(grasps), str(tmp_path / "g" / "x.obj"))


def test_an_open_mesh_warns_once_what_the_contact_model_cannot_do(cli, tmp_path):
    grasps = _grasp_file(tmp_path / "g")
    box = trimesh.creation.box(extents=(0.05, 0.05, 0.1))
    top = np.flatnonzero(box.face_normals[:, 2] > 0.9)
    box.update_faces(np.setdiff1d(np.arange(len(box.faces)), top))  # an open box
    assert not box.is_watertight
    box.export(tmp_path / "g" / "x.obj")
    code, _, err = cli("validate", _config(tmp_path, grasps))
    assert code == 0, err
    assert err.count("not watertight") == 1, err
    assert "cannot tell whether a gripper piece lies wholly inside it" in err
    assert str(tmp_path / "g" / "x.obj") in err


def test_an_out_of_range_stable_pose_is_one_line(cli, tmp_path):
    grasps = _grasp_file(tmp_path / "g")
    trimesh.creation.box(extents=(0.05, 0.05, 0.1)).export(tmp_path / "g" / "x.obj")
    code, _, err = cli("validate", _config(tmp_path, grasps, placement={"stable_pose": 40}))
    assert_one_line_error(code, err, "candidates.placement.stable_pose: 40 is out of range")


def test_an_open_object_mesh_in_the_config_warns_once_too(cli, tmp_path):
    box = trimesh.creation.box(extents=(0.05, 0.05, 0.1))
    box.update_faces(np.flatnonzero(box.face_normals[:, 2] < 0.9))  # no lid
    box.export(tmp_path / "open.obj")
    grasps = tmp_path / "g.npy"
    t = np.tile(np.eye(4), (3, 1, 1))
    t[:, 0, 3] = [0.0, 0.01, 0.02]
    np.save(grasps, t)
    for source in ("file", "antipodal"):
        cand = {"source": source, "path": str(grasps), "frame": "object"}
        if source == "antipodal":
            cand = {"source": "antipodal", "count": 4}
        cfg = tmp_path / f"{source}.yaml"
        cfg.write_text(
            yaml.safe_dump(
                {
                    "object": {"shape": "mesh", "mesh": str(tmp_path / "open.obj")},
                    "candidates": cand,
                }
            )
        )
        code, _, err = cli("validate", cfg)
        assert code == 0, err
        assert err.count("not watertight") == 1, (source, err)
        assert "contact model cannot tell whether a gripper piece lies wholly inside" in err


def test_run_says_which_object_it_placed(cli, tmp_path):
    grasps = _grasp_file(tmp_path / "data" / "grasps")
    (tmp_path / "data" / "meshes" / "Box").mkdir(parents=True)
    trimesh.creation.box(extents=(0.05, 0.05, 0.1)).export(tmp_path / "data/meshes/Box/x.obj")
    cfg = _config(tmp_path, grasps, placement={"xy": [0.4, 0.1]})
    out = tmp_path / "run"
    code, text, err = cli("run", cfg, "--out", out, *QUICK)
    assert code == 0, err
    assert "  object        x.obj (named by the file) at [0.4, 0.1]" in text
    saved = yaml.safe_load((out / "config.yaml").read_text())  # re-runs the same scene
    assert saved["object"]["mesh"] == str(tmp_path / "data/meshes/Box/x.obj")
    assert saved["candidates"]["frame"] == "object"


def test_a_flat_mesh_is_one_line(cli, tmp_path):
    grasps = _grasp_file(tmp_path / "g")
    (tmp_path / "g" / "x.obj").write_text("v 0 0 0\nv 0.1 0 0\nv 0 0.1 0\nf 1 2 3\n")
    code, _, err = cli("validate", _config(tmp_path, grasps))
    assert_one_line_error(
        code, err, str(grasps), "object/file", "the mesh has no stable pose on a table"
    )


def test_a_file_that_labels_success_keeps_the_successful_grasps_and_says_so(cli, tmp_path):
    """ACRONYM's negatives are grasps its simulation saw fail: not candidates by default."""
    grasps = _grasp_file(tmp_path / "data" / "grasps")
    with h5py.File(grasps, "r+") as f:  # a fourth grasp, labelled failed
        t = np.concatenate([f["grasps/transforms"][()], f["grasps/transforms"][:1]])
        t[3, 2, 3] = 0.25
        del f["grasps/transforms"], f["grasps/qualities/flex/object_in_gripper"]
        f["grasps/transforms"] = t
        f["grasps/qualities/flex/object_in_gripper"] = np.array([1.0, 1.0, 1.0, 0.0])
    (tmp_path / "data" / "meshes" / "Box").mkdir(parents=True)
    trimesh.creation.box(extents=(0.05, 0.05, 0.1)).export(tmp_path / "data/meshes/Box/x.obj")
    for extra, kept, note in (
        ({}, [0, 1, 2], " (of 4 in the file: labelled successful)"),
        ({"success_only": False}, [0, 1, 2, 3], ""),
    ):
        out = tmp_path / f"run{len(kept)}"
        code, text, err = cli("run", _config(tmp_path, grasps, **extra), "--out", out, *QUICK)
        assert code == 0, err
        assert f"  candidates    {len(kept)}{note}\n" in text
        table = np.genfromtxt(out / "grasps.csv", delimiter=",", names=True, dtype=None)
        origin = table["origin"].astype(str)
        assert sorted(table["source_id"][origin == "candidate"].tolist()) == kept
