"""A study moves an object its grasp file names (ACRONYM) as it moves a configured object.

The base is ``configs/acronym_mug.yaml``: no ``object`` section, the mug and its
scale come from the grasp file and stand on the table by
``candidates.placement``. A swept ``x, y, yaw_deg`` moves that placement (the
centre of the mug's footprint and its turn about the vertical); a swept ``z``
is refused, the stable pose fixes the height. Every placement runs in this
process (``engine="inline"``), no Ray.
"""

from __future__ import annotations

import shutil

import numpy as np
import pytest
import yaml
from helpers import CONFIGS, assert_one_line_error

from gcm_pipeline.cli import main
from gcm_pipeline.config import load_config
from gcm_pipeline.errors import ConfigError
from gcm_pipeline.geometry.dualquat import dq_to_pos_quat
from gcm_pipeline.pipeline import Pipeline, place_file_object
from gcm_pipeline.study import Study, load_study

MUG = CONFIGS / "acronym_mug.yaml"
#: The 30 best grasps of the file, one subdivision (interpolated rows too), no scene.
SMALL = [
    "candidates.limit=30",
    "densify.subdivisions=2",
    "publish.html=false",
    "publish.plots=false",
]


def _pose7(dq: np.ndarray) -> np.ndarray:
    pos, quat = dq_to_pos_quat(dq)
    return np.concatenate([pos, np.where(quat[:, :1] < 0, -quat, quat)], axis=1)


def _matrix(pose7: np.ndarray) -> np.ndarray:
    """(N, 4, 4) of poses ``x, y, z, qw, qx, qy, qz``."""
    from scipy.spatial.transform import Rotation

    m = np.tile(np.eye(4), (len(pose7), 1, 1))
    m[:, :3, :3] = Rotation.from_quat(pose7[:, [4, 5, 6, 3]]).as_matrix()
    m[:, :3, 3] = pose7[:, :3]
    return m


def _arrays(out, pid: int) -> dict[str, np.ndarray]:
    """The arrays of placement ``pid`` as the study stored them."""
    with np.load(out / "placements" / f"{pid:06d}.npz") as data:
        return {k: data[k] for k in data.files if k != "row"}


def test_the_sweep_moves_the_placement_of_the_file_object():
    study = Study.from_dict(
        {
            "base": str(MUG),
            "sweep": {
                "object_pose": {"x": [0.4, 0.55, 3.0], "yaw_deg": [0, 90], "region": "table"}
            },
        }
    )
    grid = study.placements()
    assert len(grid) == 4  # x 3.0 lies off the table
    assert grid[1].overrides == (
        "candidates.placement.xy=[0.4, 0.0]",
        "candidates.placement.yaw_deg=90.0",
    )
    placed = [place_file_object(study.plan.resolve(p.overrides)) for p in grid]
    for p, cfg in zip(grid, placed, strict=True):
        assert cfg.candidates.placement.xy == (p.object_pose["x"], 0.0)
        assert cfg.candidates.placement.yaw_deg == p.object_pose["yaw_deg"]
    # the mug itself moves: 15 cm along x, a quarter turn about the vertical
    m = [cfg.object.pose.matrix() for cfg in placed]
    assert np.allclose(m[2][:3, 3] - m[0][:3, 3], [0.15, 0.0, 0.0], atol=1e-9)
    assert np.allclose(m[0][:3, :3], m[2][:3, :3], atol=1e-12)
    quarter = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    assert np.allclose(m[1][:3, :3], quarter @ m[0][:3, :3], atol=1e-9)


def test_a_study_of_the_file_object_matches_a_run_at_its_best_placement(tmp_path):
    data = {
        "base": str(MUG),
        "set": SMALL,
        "sweep": {"object_pose": {"x": [0.4, 0.55], "yaw_deg": [0, 90]}},
    }
    out = tmp_path / "study"
    result = Study.from_dict(data).run(out, engine="inline", progress=False, best_run=False)
    assert result.complete and not result.failed and len(result.rows) == 4
    rows = sorted(result.rows, key=lambda r: r["id"])
    table_z = load_config(MUG).environment.table.height
    for r in rows:  # the pose columns: where the mug stands (y and z not swept)
        assert (r["object_y"], r["object_z"]) == (0.0, table_z)
    # the grasps move with the mug: every row (interpolated too) has the same pose in the
    # mug's frame at every placement (reachability.npz's same_grasps), and is the placed
    # mug's pose times that pose (reachability.npz's grasp_pose_object)
    arrays = {r["id"]: _arrays(out, r["id"]) for r in rows}
    first = arrays[rows[0]["id"]]
    local = _matrix(first["pose_object"][first["is_candidate"]])
    assert len(local) == 30 and all(r["densified"] > 30 for r in rows)
    for r in rows:
        a = arrays[r["id"]]
        assert np.allclose(_matrix(a["pose_object"][a["is_candidate"]]), local, atol=1e-9)
        # and the densified rows too, row by row: the manifold does not turn with the mug
        assert np.allclose(_matrix(a["pose_object"]), _matrix(first["pose_object"]), atol=1e-9)
        cfg = place_file_object(load_config(MUG, list(r["overrides"])))
        world = cfg.object.pose.matrix() @ _matrix(a["pose_object"])
        assert np.allclose(world, _matrix(a["pose"]), atol=1e-9)
    # the best placement is what gcm run gives at that placement
    best = result.best
    assert best["reachable"] == max(r["reachable"] for r in rows)
    run = Pipeline(load_config(MUG, list(best["overrides"]))).run(progress=False, write=False)
    grasps = run.grasps
    a = arrays[best["id"]]
    pose = _pose7(grasps["dq"])
    order_run = np.lexsort(np.round(pose, 9).T[::-1])
    order_study = np.lexsort(np.round(a["pose"], 9).T[::-1])
    assert np.allclose(pose[order_run], a["pose"][order_study], atol=1e-12)
    reach = np.asarray(grasps["reachable"], dtype=bool)
    assert reach.sum() == best["reachable"]
    assert np.array_equal(reach[order_run], a["reachable_mask"][order_study])
    manip = np.asarray(grasps["manipulability"], dtype=float)[order_run][reach[order_run]]
    assert np.allclose(manip, a["manipulability"][order_study][reach[order_run]], rtol=1e-12)


def test_sweeping_the_height_of_a_file_object_is_one_line(tmp_path, capsys):
    data = {"base": str(MUG), "sweep": {"object_pose": {"x": [0.5], "z": [0.0, 0.1]}}}
    with pytest.raises(ConfigError, match=r"sweep\.object_pose\.z: object: .*stable pose"):
        load_study(data)
    path = tmp_path / "study.yaml"
    path.write_text(yaml.safe_dump(data))
    out = tmp_path / "out"
    code = main(["study", str(path), "--out", str(out)])
    assert_one_line_error(code, capsys.readouterr().err, "sweep.object_pose.z", "x, y and yaw_deg")
    assert not out.exists()


def test_the_example_study_of_the_acronym_mug_plans_its_grid():
    study = Study.from_yaml(CONFIGS / "studies" / "acronym_mug_placement.yaml")
    grid = study.placements()
    assert len(grid) == 36
    assert grid[-1].overrides[-2:] == (
        "candidates.placement.xy=[0.65, 0.25]",
        "candidates.placement.yaw_deg=270.0",
    )


def test_a_study_file_given_as_a_run_config_says_what_it_is(capsys):
    path = CONFIGS / "studies" / "acronym_mug_placement.yaml"
    code = main(["run", str(path)])
    assert_one_line_error(
        code, capsys.readouterr().err, "a placement study (base, sweep)", f"gcm study {path}"
    )
    # gcm validate checks it as a study file
    assert main(["validate", str(path)]) == 0
    text = capsys.readouterr().out
    assert f"# {path}: ok (a study file)\n" in text
    assert "#   placements  36;" in text


def test_the_study_key_covers_the_mesh_the_grasp_file_names(tmp_path):
    """Another mesh under the same name is another study (a rerun does not resume it)."""
    data_dir = tmp_path / "acronym"
    shutil.copytree(CONFIGS.parent / "tests" / "data" / "acronym", data_dir)
    base = yaml.safe_load(MUG.read_text())
    base["candidates"]["path"] = str(next(data_dir.glob("*.h5")))
    studies = [
        {"base": base, "sweep": {"object_pose": {"x": [0.4, 0.5]}}},
        {"base": base, "sweep": {"base_pose": {"x": [0.0, -0.1]}}},  # the object not swept
    ]
    keys = [load_study(study).key() for study in studies]
    mesh = next(data_dir.glob("*.obj"))
    mesh.write_text(mesh.read_text() + "\n# the same mesh, another file\n")
    for study, key in zip(studies, keys, strict=True):
        assert load_study(study).key() != key
