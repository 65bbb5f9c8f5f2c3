"""Several objects in one run: the target's grasps, the other objects obstacles; ``target: all``."""

from __future__ import annotations

import json

import numpy as np
import pytest
import yaml
from helpers import CONFIGS, QUICK, assert_one_line_error, decode_commands

from gcm_pipeline.config import Config, load_config
from gcm_pipeline.errors import ConfigError, OutputError
from gcm_pipeline.geometry.dualquat import dq_to_pos_quat
from gcm_pipeline.pipeline import (
    Pipeline,
    generate_candidates,
    make_checker,
    run_objects,
    target_config,
)
from gcm_pipeline.rundir.run import read_run

TWO = CONFIGS / "two_objects.yaml"


def _data() -> dict:
    return yaml.safe_load(TWO.read_text())


def _xyz(grasps) -> np.ndarray:
    """The grasp positions (N, 3) [m]."""
    return dq_to_pos_quat(grasps["dq"])[0]


def _run(data: dict):
    return Pipeline(Config.from_dict(data)).run(write=False, progress=False)


@pytest.fixture(scope="module")
def bottle_alone():
    """The bottle's grasps with the bottle alone on the table (the classic ``object``)."""
    data = _data()
    data["object"] = {k: v for k, v in data.pop("objects")[0].items() if k != "name"}
    del data["target"]
    return _run(data)


@pytest.fixture(scope="module")
def bottle_and_can():
    return _run(_data())


def test_the_other_object_blocks_grasps_of_the_target(bottle_alone, bottle_and_can):
    alone, both = bottle_alone.grasps, bottle_and_can.grasps
    # the same grasps of the same object: only the world differs
    assert np.array_equal(alone["dq"], both["dq"])
    was, now = np.asarray(alone["reachable"]), np.asarray(both["reachable"])
    blocked = was & ~now
    assert bottle_and_can.counts["reachable"] < bottle_alone.counts["reachable"]
    assert blocked.sum() >= 10, blocked.sum()
    reasons = np.asarray(both["reason"])[blocked]
    assert set(reasons) <= {"collision_environment", "approach"}, set(reasons)
    assert (reasons == "collision_environment").mean() > 0.5, reasons
    # the blocked grasps are on the can's side (+y) of the bottle
    assert np.mean(np.sign(_xyz(both)[blocked, 1])) > 0.8
    # and what their arm hits is the can (the rejected solution, checked on its own)
    checker = make_checker(
        bottle_and_can.robot, bottle_and_can.config.environment, bottle_and_can.config.object
    )
    for i in np.flatnonzero(blocked & (np.asarray(both["reason"]) == "collision_environment")):
        pairs = checker.colliding_pairs(both["q_rejected"][i])
        assert any("can" in (a, b) for a, b, _ in pairs), pairs


def test_the_target_is_the_object_not_an_obstacle(bottle_alone):
    """``objects`` with the bottle alone runs exactly as ``object``: the contact model applies."""
    data = _data()
    data["objects"] = data["objects"][:1]
    one = _run(data)
    assert np.array_equal(one.grasps["reachable"], bottle_alone.grasps["reachable"])
    assert list(one.grasps["reason"]) == list(bottle_alone.grasps["reason"])
    assert one.config.object == bottle_alone.config.object
    assert one.config.environment.obstacles == ()


def test_the_run_records_the_target_as_object_and_the_others_as_obstacles(bottle_and_can):
    cfg = bottle_and_can.config
    assert cfg.objects is None and cfg.target is None
    assert cfg.object.shape == "cylinder" and cfg.object.dims.height == 0.22
    (can,) = cfg.environment.obstacles
    assert can.name == "can" and can.pose.xyz == (0.5, 0.11, 0.0)
    # the recorded config runs as it ran
    assert target_config(cfg) is cfg


def test_target_all_gives_each_object_its_own_run(cli, tmp_path):
    out = tmp_path / "all"
    code, text, err = cli("run", TWO, "--target", "all", "--out", out, *QUICK)
    assert code == 0, err
    summary = json.loads((out / "summary.json").read_text())
    assert list(summary["objects"]) == ["bottle", "can"]
    assert Config.from_dict(yaml.safe_load((out / "config.yaml").read_text())).target == "all"
    centres = {"bottle": (0.5, 0.0), "can": (0.5, 0.11)}
    for name, other in (("bottle", "can"), ("can", "bottle")):
        run = read_run(out / "objects" / name)
        entry = summary["objects"][name]
        assert entry["reachable"] == int(np.count_nonzero(run.grasps["reachable"])) > 0
        assert entry["densified"] == len(run.grasps)
        cfg = Config.from_dict(yaml.safe_load((out / "objects" / name / "config.yaml").read_text()))
        assert cfg.object.pose.xyz[:2] == centres[name]
        assert [o.name for o in cfg.environment.obstacles] == [other]
        # the candidates are this object's: on a ring around its axis
        xy = _xyz(run.grasps)[: entry["candidates"], :2]
        radius = np.linalg.norm(xy - centres[name], axis=1)
        assert np.ptp(radius) < 0.01, radius
        assert "collision_environment" in entry["unreachable_by_reason"]
        code, text, err = cli("show", out / "objects" / name)
        assert code == 0, err
    code, _, err = cli("show", out)
    assert_one_line_error(code, err, "objects/", "bottle, can")
    code, _, err = cli("export", out, "--format", "npz")
    assert_one_line_error(code, err, "objects/", "bottle, can")
    assert not (out / "grasps.npz").exists()


@pytest.mark.parametrize("how", [("--meshcat",), ("--set", "publish.meshcat=true")])
def test_target_all_with_the_live_viewer_says_how_to_view_one(cli, tmp_path, how):
    out = tmp_path / "all"
    code, text, err = cli("run", TWO, "--target", "all", "--out", out, *how)
    key = "--meshcat" if how == ("--meshcat",) else "publish.meshcat"
    line = assert_one_line_error(code, err, key, "bottle, can", "--target NAME", "gcm view")
    assert "gcm show" not in line  # it has no live viewer
    assert text == "" and not out.exists()


def test_run_objects_matches_the_single_target_run(tmp_path, bottle_and_can):
    cfg = load_config(TWO, ["target=all", "publish.html=false"])
    result = run_objects(cfg, tmp_path / "all", progress=False)
    bottle = result.results["bottle"]
    assert bottle.run_dir == tmp_path / "all" / "objects" / "bottle"
    assert np.array_equal(bottle.grasps["reachable"], bottle_and_can.grasps["reachable"])
    # a previous objects directory is replaced with force only; it is no run directory
    with pytest.raises(OutputError, match="already exists"):
        run_objects(cfg, tmp_path / "all", progress=False)
    again = run_objects(cfg, tmp_path / "all", progress=False, force=True)
    assert again.run_dir == tmp_path / "all" and len(again.results) == 2
    with pytest.raises(OutputError, match="objects directory, not a run directory"):
        Pipeline(target_config(cfg, "can")).run(tmp_path / "all", progress=False, force=True)
    single = tmp_path / "single"
    Pipeline(target_config(cfg, "can")).run(single, progress=False)
    with pytest.raises(OutputError, match="a gcm run directory, not an objects directory;"):
        run_objects(cfg, single, progress=False, force=True)


def test_pipeline_run_refuses_target_all():
    with pytest.raises(ConfigError, match="target: 'all'"):
        Pipeline(load_config(TWO, ["target=all"])).run(write=False, progress=False)


def _objects(**extra):
    """Two named cylinders (and ``extra`` keys of the config)."""
    obj = {"shape": "cylinder", "dims": {"radius": 0.03, "height": 0.1}}
    return {
        "objects": [
            {**obj, "name": "a", "pose": {"xyz": [0.5, 0.0, 0.0]}},
            {**obj, "name": "b", "pose": {"xyz": [0.5, 0.2, 0.0]}},
        ],
        "target": "a",
        "candidates": {"source": "cylinder_side", "count": 9},
        **extra,
    }


def _swap(data, key, value):
    data = json.loads(json.dumps(data))
    node = data
    *path, last = key
    for k in path:
        node = node[k]
    if value is None:
        del node[last]
    else:
        node[last] = value
    return data


BAD = {
    "unknown target": (("target",), "mug", ["unknown target 'mug'", "valid: a, all, b"]),
    "duplicate name": (("objects", 1, "name"), "a", ["objects.1.name", "'a' is used twice"]),
    "name differing in case": (("objects", 1, "name"), "A", ["objects.1.name", "'A'", "case"]),
    "reserved name": (("objects", 0, "name"), "all", ["objects.0.name", "'all' is reserved"]),
    "bad name": (("objects", 0, "name"), "a/b", ["objects.0.name", "a/b"]),
    "empty list": (("objects",), [], ["objects: the list is empty"]),
    "no target": (("target",), None, ["give 'target'", "a, b or 'all'"]),
    "object too": (("object",), {"shape": "sphere", "dims": {"radius": 0.02}}, ["not both"]),
    "plane obstacle": (
        ("objects", 1),
        {"name": "tray", "shape": "plane", "dims": {"size": [0.2, 0.2]}},
        ["objects.1 (tray)", "plane"],
    ),
    "shape for generator": (
        ("objects", 0),
        {"name": "a", "shape": "sphere", "dims": {"radius": 0.02}},
        ["objects[a].shape 'sphere'", "cylinder_side"],
    ),
}


@pytest.mark.parametrize("case", sorted(BAD))
@pytest.mark.parametrize("command", ["validate", "run"])
def test_bad_objects_are_one_line_errors_and_nothing_is_written(cli, tmp_path, case, command):
    key, value, fragments = BAD[case]
    path = tmp_path / "cfg.yaml"
    path.write_text(yaml.safe_dump(_swap(_objects(), key, value)))
    out = tmp_path / "out"
    args = ("--out", out) if command == "run" else ()
    code, text, err = cli(command, path, *args)
    assert_one_line_error(code, err, str(path), *fragments)
    assert text == "" and not out.exists()


def test_target_without_objects_is_an_error(cli, tmp_path):
    path = tmp_path / "cfg.yaml"
    data = yaml.safe_load((CONFIGS / "bottle_side.yaml").read_text())
    path.write_text(yaml.safe_dump({**data, "target": "bottle"}))
    code, text, err = cli("validate", path)
    assert_one_line_error(code, err, "target 'bottle' needs an 'objects' list")


@pytest.mark.parametrize("target", ["a", "all"])
def test_a_missing_mesh_is_named_by_its_objects_key(cli, tmp_path, target):
    data = _objects(target=target)
    data["objects"][1] = {"name": "b", "shape": "mesh", "mesh": "no/such.obj"}
    data["candidates"] = {"source": "antipodal", "count": 4}
    path = tmp_path / "cfg.yaml"
    path.write_text(yaml.safe_dump(data))
    out = tmp_path / "out"
    code, text, err = cli("run", path, "--out", out)
    assert_one_line_error(code, err, "objects.1.mesh", "no/such.obj")
    assert not out.exists()


def test_the_scene_draws_the_other_objects_as_obstacles(cli, tmp_path):
    out = tmp_path / "two"
    code, _, err = cli("run", TWO, "--out", out, "--set", "publish.plots=false")
    assert code == 0, err
    paths = {c.get("path", "") for c in decode_commands((out / "scene.html").read_text())}
    assert {"/meshcat/object/shape", "/meshcat/environment/can/shape"} <= paths
    assert not any("bottle" in p for p in paths)


def test_meshes_and_primitives_each_their_own_target(tmp_path):
    """``target: all`` over a mesh and a box, antipodal grasps sampled on each in turn."""
    data = {
        "objects": [
            {
                "name": "mug",
                "shape": "mesh",
                "mesh": str(CONFIGS / "data" / "mug.obj"),
                "pose": {"xyz": [0.5, 0.1, 0.0], "rpy_deg": [0, 0, 150]},
            },
            {
                "name": "block",
                "shape": "box",
                "dims": {"size": [0.06, 0.06, 0.15]},
                "pose": {"xyz": [0.5, 0.0, 0.075]},
            },
        ],
        "target": "all",
        "candidates": {"source": "antipodal", "count": 40, "gripper": "franka_panda"},
        "densify": {"subdivisions": 2},
        "publish": {"html": False, "plots": False},
    }
    result = run_objects(Config.from_dict(data), tmp_path / "all", progress=False)
    mug, block = result.results["mug"], result.results["block"]
    assert mug.config.object.shape == "mesh" and block.config.object.shape == "box"
    assert [o.shape for o in block.config.environment.obstacles] == ["mesh"]
    centres = {"mug": (0.5, 0.1), "block": (0.5, 0.0)}
    for name, run in result.results.items():
        assert run.counts["reachable"] > 0
        # the candidates are sampled on this object: nearer its centre than the other's
        xy = _xyz(run.grasps)[: run.counts["candidates"], :2]
        (other_centre,) = [c for n, c in centres.items() if n != name]
        own = np.linalg.norm(xy - centres[name], axis=1)
        other = np.linalg.norm(xy - other_centre, axis=1)
        assert own.mean() < other.mean() and own.max() < 0.1, (name, own, other)
    assert np.linalg.norm(_xyz(block.grasps)[:, :2] - centres["block"], axis=1).max() < 0.05
    # a grasp of the block the mug (a mesh obstacle) blocks
    reasons = np.asarray(block.grasps["reason"])
    checker = make_checker(block.robot, block.config.environment, block.config.object)
    hits = [
        any("mug" in (a, b) for a, b, _ in checker.colliding_pairs(block.grasps["q_rejected"][i]))
        for i in np.flatnonzero(reasons == "collision_environment")
    ]
    assert any(hits), reasons


@pytest.mark.parametrize("target", ["a", "b"])
def test_a_grasp_file_in_the_object_frame_follows_the_target(tmp_path, target):
    poses = np.tile(np.eye(4), (3, 1, 1))
    poses[:, :3, 3] = [[0.0, 0.0, 0.05], [0.01, 0.0, 0.06], [0.0, 0.01, 0.07]]
    np.save(tmp_path / "g.npy", poses)
    data = _objects(target=target)
    data["candidates"] = {"source": "file", "path": str(tmp_path / "g.npy"), "frame": "object"}
    cfg = target_config(Config.from_dict(data))
    xyz = _xyz(generate_candidates(cfg))
    origin = {"a": [0.5, 0.0, 0.0], "b": [0.5, 0.2, 0.0]}[target]
    assert np.allclose(xyz, poses[:, :3, 3] + origin)


def test_object_meshes_resolve_against_the_config_folder(tmp_path, monkeypatch):
    data = _objects()
    data["objects"][1] = {"name": "b", "shape": "mesh", "mesh": "meshes/b.obj"}
    (tmp_path / "cfgs").mkdir()
    path = tmp_path / "cfgs" / "cfg.yaml"
    path.write_text(yaml.safe_dump(data))
    monkeypatch.chdir(tmp_path)
    cfg = load_config(path)
    assert cfg.objects[1].mesh == tmp_path / "cfgs" / "meshes" / "b.obj"


def test_a_study_moving_the_object_of_an_objects_config_says_what_to_give(cli, tmp_path):
    study = tmp_path / "study.yaml"
    study.write_text(
        yaml.safe_dump({"base": str(TWO), "sweep": {"object_pose": {"x": [0.4, 0.5]}}})
    )
    out = tmp_path / "study"
    code, text, err = cli("study", study, "--out", out, "--workers", "1")
    assert_one_line_error(
        code, err, "sweep.object_pose", "'objects'", "target 'bottle'", "base_pose"
    )
    assert not out.exists()


def test_an_object_without_a_candidate_under_target_all_is_named_and_nothing_written(cli, tmp_path):
    data = _objects(target="all")
    data["objects"][1] = {
        "name": "boulder",
        "shape": "sphere",
        "dims": {"radius": 0.3},
        "pose": {"xyz": [0.5, 0.8, 0.3]},
    }
    data["candidates"] = {"source": "antipodal", "count": 4}
    path = tmp_path / "cfg.yaml"
    path.write_text(yaml.safe_dump(data))
    out = tmp_path / "out"
    code, text, err = cli("run", path, "--out", out, *QUICK)
    assert_one_line_error(
        code, err, "objects[boulder]: ", "no collision-free antipodal grasp", warnings=True
    )
    assert not out.exists()
