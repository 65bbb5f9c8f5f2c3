"""Config: loading, validation errors with suggestions, overrides, poses, schema."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
from helpers import ROOT
from scipy.spatial.transform import Rotation

from gcm_pipeline.config import Config, Pose, config_schema, load_config
from gcm_pipeline.errors import ConfigError

CONFIGS = sorted((ROOT / "configs").glob("*.yaml"))

BASE = {
    "object": {"shape": "cylinder", "dims": {"radius": 0.03, "height": 0.2}},
    "candidates": {"source": "cylinder_side"},
}


def _with(**sections):
    data = json.loads(json.dumps(BASE))
    data.update(sections)
    return data


def _error(data) -> str:
    with pytest.raises(ConfigError) as info:
        Config.from_dict(data)
    return str(info.value)


@pytest.mark.parametrize("path", CONFIGS, ids=lambda p: p.name)
def test_example_configs_load(path):
    cfg = load_config(path)
    assert isinstance(cfg, Config)
    # the resolved config round-trips through plain data
    assert Config.from_dict(cfg.to_dict()) == cfg


def test_defaults_and_frozen():
    cfg = Config.from_dict(BASE)
    assert cfg.seed == 0 and cfg.robot.spec == "panda" and cfg.ik.backend == "pinocchio"
    with pytest.raises(Exception):  # noqa: B017 - pydantic's frozen-instance error
        cfg.seed = 3  # type: ignore[misc]
    with pytest.raises(Exception):  # noqa: B017
        cfg.ik.backend = "mink"  # type: ignore[misc]


def test_repr_is_readable():
    cfg = Config.from_dict(BASE)
    text = repr(cfg.candidates)
    assert text.startswith("CandidatesConfig(") and "cylinder_side" in text


@pytest.mark.parametrize(
    ("data", "expected"),
    [
        ({**BASE, "candidats": {}}, "unknown key 'candidats' (did you mean 'candidates'?)"),
        (
            _with(manifold={"projecton": "xy"}),
            "unknown key 'manifold.projecton' (did you mean 'manifold.projection'?)",
        ),
        (
            _with(environment={"table": {"heigth": 0.1}}),
            "did you mean 'environment.table.height'?",
        ),
        (
            _with(
                environment={
                    "obstacles": [{"shape": "box", "dims": {"size": [1, 1, 1]}, "poze": {}}]
                }
            ),
            "did you mean 'environment.obstacles.0.pose'?",
        ),
        (
            _with(
                object={
                    "shape": "cylinder",
                    "dims": {"radius": 1, "height": 1},
                    "pose": {"rpyy": [0, 0, 0]},
                }
            ),
            "did you mean 'object.pose.rpy'?",
        ),
    ],
)
def test_unknown_keys_suggest_the_closest(data, expected):
    msg = _error(data)
    assert expected in msg
    assert "valid keys here:" in msg


@pytest.mark.parametrize(
    ("mutate", "expected"),
    [
        (lambda d: d["candidates"].update(count=0), "candidates.count"),
        (lambda d: d["candidates"].update(count=-5), "candidates.count"),
        (lambda d: d["candidates"].update(count="many"), "candidates.count"),
        (lambda d: d["candidates"].update(count=2.5), "candidates.count"),
        (lambda d: d["object"]["dims"].update(radius=0), "object.dims.radius"),
        (lambda d: d["object"]["dims"].update(height=-0.1), "object.dims.height"),
        (lambda d: d["candidates"].update(noise={"position": -1}), "candidates.noise.position"),
        (lambda d: d.update(densify={"subdivisions": 0}), "densify.subdivisions"),
        (lambda d: d.update(densify={"subdivisions": None}), "densify: give 'subdivisions'"),
        (lambda d: d.update(manifold={"max_edge_length": -1}), "manifold.max_edge_length"),
        (lambda d: d.update(ik={"position_tolerance": 0}), "ik.position_tolerance"),
        (lambda d: d.update(seed="x"), "seed"),
        (
            lambda d: d["object"].update(pose={"xyz": [0, 0]}),
            "object.pose.xyz: expected 3 values, got 2",
        ),
        (lambda d: d.update(environment={"table": 5}), "environment.table: expected a mapping"),
        (lambda d: d.update(object={"shape": "box", "dims": {"size": [1, 2]}}), "3 values"),
        (lambda d: d.update(object={"shape": "box"}), "shape 'box' needs dims.size"),
        (lambda d: d.update(object=None), "needs object.shape 'cylinder'"),
        (lambda d: d["object"].update(shape="sphere", dims={"radius": 1}), "needs object.shape"),
        (lambda d: d.update(candidates={"source": "file"}), "needs 'path'"),
        (lambda d: d.update(publish={"zmq_url": "notaurl"}), "publish.zmq_url: expected tcp://"),
        (lambda d: d.update(publish={"zmq_url": "tcp://127.0.0.1"}), "publish.zmq_url"),
        (lambda d: d.update(publish={"zmq_url": "tcp://host:99999"}), "publish.zmq_url"),
        (lambda d: d.update(publish={"zmq_url": "http://host:6000"}), "publish.zmq_url"),
    ],
)
def test_bad_values_name_the_key(mutate, expected):
    data = json.loads(json.dumps(BASE))
    mutate(data)
    assert expected in _error(data)


def test_bad_choice_suggests_and_lists():
    msg = _error(_with(candidates={"source": "cylinder"}))
    assert "candidates.source" in msg and "did you mean 'cylinder_side'?" in msg
    assert "box, cylinder_side, file, plane, sphere" in msg
    msg = _error(_with(ik={"backend": "minc"}))
    assert "did you mean 'mink'?" in msg


def test_empty_and_non_mapping_configs(tmp_path):
    empty = tmp_path / "empty.yaml"
    empty.write_text("")
    with pytest.raises(ConfigError, match="empty"):
        load_config(empty)
    listy = tmp_path / "list.yaml"
    listy.write_text("- a\n- b\n")
    with pytest.raises(ConfigError, match="mapping"):
        load_config(listy)


def test_missing_file(tmp_path):
    with pytest.raises(ConfigError, match="not found"):
        load_config(tmp_path / "nope.yaml")


def test_malformed_yaml_names_line_and_column(tmp_path):
    bad = tmp_path / "bad.yaml"
    bad.write_text("seed: 0\ncandidates:\n  source: plane\n  count: [1, 2\n")
    with pytest.raises(ConfigError) as info:
        load_config(bad)
    msg = str(info.value)
    assert str(bad) in msg and "malformed YAML" in msg
    assert ":5:1" in msg or ":4:" in msg


def test_overrides_apply_to_any_key():
    cfg = load_config(
        ROOT / "configs" / "bottle_side.yaml",
        ["ik.backend=mink", "densify.subdivisions=6", "object.pose.xyz=[0.4, 0.1, 0]", "seed=7"],
    )
    assert cfg.ik.backend == "mink"
    assert cfg.densify.subdivisions == 6
    assert cfg.object is not None and cfg.object.pose.xyz == (0.4, 0.1, 0.0)
    assert cfg.seed == 7
    # a section that the file does not have is created
    cfg = load_config(ROOT / "configs" / "flat_surface.yaml", ["approach.distance=0.05"])
    assert cfg.approach is not None and cfg.approach.distance == 0.05


def test_overrides_reach_an_entry_of_a_list():
    """``--set environment.point_clouds.0.voxel_size=0.02``: a list entry by its index."""
    clutter = ROOT / "configs" / "clutter_scene.yaml"
    cfg = load_config(clutter, ["environment.point_clouds.0.voxel_size=0.02"])
    assert cfg.environment.point_clouds[0].voxel_size == 0.02
    assert cfg.environment.point_clouds[0].exclude_segments == (1,)  # the rest kept
    cfg = load_config(clutter, ["environment.point_clouds.0={path: x.npy, frame: world}"])
    assert cfg.environment.point_clouds[0].frame == "world"
    for bad, said in [
        ("environment.point_clouds.1.voxel_size=0.02", "a list of 1 entry; give an index from 0"),
        ("environment.point_clouds.x=0.02", "got 'x'"),
        ("environment.point_clouds.-1.name=a", "got '-1'"),
    ]:
        with pytest.raises(ConfigError, match="environment.point_clouds' is a list") as info:
            load_config(clutter, [bad])
        assert said in str(info.value)
    with pytest.raises(ConfigError, match="is an empty list; set the whole list"):
        load_config(clutter, ["environment.point_clouds=[]", "environment.point_clouds.0.name=a"])


@pytest.mark.parametrize(
    ("override", "expected"),
    [
        ("ik.backnd=mink", "unknown key 'ik.backnd' (did you mean 'ik.backend'?)"),
        ("densfy.subdivisions=3", "unknown key 'densfy' (did you mean 'densify'?)"),
        ("densify.subdivisions=-1", "densify.subdivisions"),
        ("ik.backend", "expected KEY=VALUE"),
        ("seed.x=1", "'seed' is not a section"),
    ],
)
def test_bad_overrides(override, expected):
    with pytest.raises(ConfigError) as info:
        load_config(ROOT / "configs" / "bottle_side.yaml", [override])
    assert expected in str(info.value)


def test_relative_paths_resolve_against_the_config(tmp_path):
    cfg = load_config(ROOT / "configs" / "from_file.yaml")
    assert cfg.candidates.path is not None and cfg.candidates.path.is_file()


@pytest.mark.parametrize("rpy", [(0.1, -0.4, 2.0), (math.pi / 2, 0.3, -1.0), (0.0, 0.0, 0.0)])
def test_pose_rpy_matches_fixed_axis_xyz(rpy):
    m = Pose(xyz=(1, 2, 3), rpy=rpy).matrix()
    assert np.allclose(m[:3, :3], Rotation.from_euler("xyz", rpy).as_matrix())
    assert np.allclose(m[:3, 3], [1, 2, 3])
    deg = Pose(xyz=(1, 2, 3), rpy_deg=tuple(np.degrees(rpy))).matrix()
    assert np.allclose(deg, m)


def test_pose_rejects_both_rotations():
    msg = _error(
        _with(
            object={
                "shape": "sphere",
                "dims": {"radius": 0.1},
                "pose": {"rpy": [0, 0, 0], "rpy_deg": [0, 0, 0]},
            },
            candidates={"source": "sphere"},
        )
    )
    assert "either 'rpy'" in msg


def test_schema_is_json_and_strict():
    schema = config_schema()
    text = json.dumps(schema)
    assert "candidates" in schema["properties"]
    assert schema["required"] == ["candidates"]
    assert schema["additionalProperties"] is False
    assert "cylinder_side" in text


def test_relative_paths_prefer_the_config_directory(tmp_path, monkeypatch):
    (tmp_path / "cfg").mkdir()
    (tmp_path / "cfg" / "g.npy").write_bytes(b"")
    (tmp_path / "cfg" / "arm.yaml").write_text("name: x\n")
    cfg_path = tmp_path / "cfg" / "run.yaml"
    cfg_path.write_text(
        "robot: {spec: arm.yaml}\ncandidates: {source: file, path: g.npy}\n"
        "environment: {obstacles: [{shape: mesh, mesh: missing.stl}]}\n"
    )
    monkeypatch.chdir(tmp_path)
    cfg = load_config(cfg_path)
    assert cfg.candidates.path == tmp_path / "cfg" / "g.npy"
    assert cfg.robot.spec == str(tmp_path / "cfg" / "arm.yaml")
    # a missing file is reported where the config says it is
    assert cfg.environment.obstacles[0].mesh == tmp_path / "cfg" / "missing.stl"
    # a shipped robot name stays a name
    assert load_config(ROOT / "configs" / "box.yaml").robot.spec == "panda"


@pytest.mark.parametrize("url", ["tcp://127.0.0.1:6000", "tcp://localhost:1", "tcp://[::1]:6000"])
def test_good_zmq_urls(url):
    assert Config.from_dict(_with(publish={"zmq_url": url})).publish.zmq_url == url


def test_file_paths_become_absolute(tmp_path, monkeypatch):
    """The resolved config reads the same files from any working directory."""
    monkeypatch.chdir(ROOT)
    cfg = load_config(Path("configs") / "from_file.yaml")
    assert cfg.candidates.path == ROOT / "configs" / "data" / "mug_grasps.npy"
    assert cfg.to_dict()["candidates"]["path"] == str(ROOT / "configs" / "data" / "mug_grasps.npy")
    (tmp_path / "m.stl").write_text("")
    monkeypatch.chdir(tmp_path)
    data = {
        "object": {"shape": "mesh", "mesh": "m.stl"},
        "candidates": {"source": "file", "path": "sub/../g.npy"},
        "environment": {"obstacles": [{"shape": "mesh", "mesh": "m.stl"}]},
        "robot": {"spec": "arms/arm.yaml"},
    }
    cfg = Config.from_dict(data)
    assert cfg.object is not None and cfg.object.mesh == tmp_path / "m.stl"
    assert cfg.candidates.path == tmp_path / "g.npy"
    assert cfg.environment.obstacles[0].mesh == tmp_path / "m.stl"
    assert cfg.robot.spec == str(tmp_path / "arms" / "arm.yaml")
    assert data["candidates"]["path"] == "sub/../g.npy"  # the input is not changed
    # the resolved config validates to itself
    assert Config.from_dict(cfg.to_dict()) == cfg


# ------------------------------------------------- strict types, limits, path rule


@pytest.mark.parametrize(
    ("override", "key"),
    [
        ("densify.subdivisions=true", "densify.subdivisions"),
        ("densify.subdivisions=4.0", "densify.subdivisions"),
        ("densify.subdivisions='4'", "densify.subdivisions"),
        ("ik.workers=1.5", "ik.workers"),
        ("publish.html=1", "publish.html"),
        ("publish.plots='yes'", "publish.plots"),
        ("ik.position_tolerance=true", "ik.position_tolerance"),
        ("ik.position_tolerance='1e-4'", "ik.position_tolerance"),
        ("object.pose.xyz=[0.4, true, 0]", "object.pose.xyz.1"),
        ("seed=-1", "seed"),
        ("candidates.seed=-3", "candidates.seed"),
        ("seed=1.0", "seed"),
    ],
)
def test_strict_types(override, key):
    with pytest.raises(ConfigError) as info:
        load_config(ROOT / "configs" / "flat_surface.yaml", [override])
    # the value came from --set: the message names it, not the config file
    assert str(info.value).startswith(f"--set {key}: ")


def test_every_number_and_switch_of_the_config_is_strict():
    """A new int/float/bool field must use the strict aliases of config.py."""
    import typing

    from pydantic import BaseModel, Strict

    def strict(meta) -> bool:
        return any(isinstance(m, Strict) and m.strict for m in meta)

    def walk(ann, meta, where, seen):
        origin = typing.get_origin(ann)
        if origin is typing.Annotated:
            base, *more = typing.get_args(ann)
            walk(base, [*meta, *more], where, seen)
        elif ann in (int, float, bool):
            assert strict(meta), f"{where} is a plain {ann.__name__}: use a strict alias"
        elif isinstance(ann, type) and issubclass(ann, BaseModel):
            if ann not in seen:
                seen.add(ann)
                for name, field in ann.model_fields.items():
                    walk(field.annotation, field.metadata, f"{ann.__name__}.{name}", seen)
        else:
            for arg in typing.get_args(ann):
                if arg is not Ellipsis and arg is not type(None):
                    walk(arg, [] if origin is not None else meta, where, seen)

    walk(Config, [], "Config", set())


def test_numpy_scalars_are_numbers():
    cfg = Config.from_dict(
        _with(seed=np.int64(3), densify={"subdivisions": np.int32(2), "spacing": None})
    )
    assert cfg.seed == 3 and cfg.densify.subdivisions == 2


def test_counts_above_their_ceiling_say_which_key_to_raise():
    msg = _error(_with(candidates={"source": "cylinder_side", "count": 10**9}))
    assert "candidates: count 1,000,000,000 is above candidates.max_count (1,000,000)" in msg
    assert "raise candidates.max_count" in msg
    cfg = Config.from_dict(
        _with(candidates={"source": "cylinder_side", "count": 2000, "max_count": 5000})
    )
    assert cfg.candidates.count == 2000
    assert "approach.steps" in _error(_with(approach={"steps": 100_000_000}))
    assert "ik.workers" in _error(_with(ik={"workers": 100_000}))


def test_messages_quote_at_most_a_few_hundred_characters():
    huge = "x" * 1_000_000
    for data in (
        _with(seed=huge),
        _with(ik={"backend": huge}),
        _with(**{huge: 1}),
        _with(object={"shape": "cylinder", "dims": {"radius": [1] * 100_000, "height": 1}}),
    ):
        msg = _error(data)
        assert len(msg) < 700, len(msg)


def test_one_path_rule_relative_to_the_config(tmp_path, monkeypatch):
    """output.dir, input files and --set values all resolve against the config's folder."""
    (tmp_path / "cfgs").mkdir()
    (tmp_path / "elsewhere").mkdir()
    cfg_path = tmp_path / "cfgs" / "my_run.yaml"
    cfg_path.write_text(
        "candidates: {source: file, path: g.npy}\nenvironment: {obstacles: []}\n"
        "output: {dir: out/a}\n"
    )
    monkeypatch.chdir(tmp_path / "elsewhere")
    cfg = load_config(cfg_path)
    assert cfg.output.dir == tmp_path / "cfgs" / "out" / "a"
    assert cfg.candidates.path == tmp_path / "cfgs" / "g.npy"
    cfg = load_config(cfg_path, ["output.dir=b", "candidates.path=h.npy"])
    assert cfg.output.dir == tmp_path / "cfgs" / "b"
    assert cfg.candidates.path == tmp_path / "cfgs" / "h.npy"
    # absolute paths stay; no output.dir: results/<config name> beside the config
    cfg = load_config(cfg_path, [f"output.dir={tmp_path}/abs", "output=null"])
    assert cfg.output.dir == tmp_path / "cfgs" / "results" / "my_run"
    cfg = load_config(cfg_path, [f"output.dir={tmp_path / 'abs'}"])
    assert cfg.output.dir == tmp_path / "abs"
    # a dict config: relative to the working directory, default results/run
    assert Config.from_dict(BASE).output.dir == tmp_path / "elsewhere" / "results" / "run"
    with pytest.raises(ConfigError, match="candidates.path: a path cannot contain a NUL"):
        load_config(cfg_path, ["candidates.path=a\0b"])


def test_an_error_in_the_file_names_the_file_and_one_from_set_names_set(tmp_path):
    bad = tmp_path / "bad.yaml"
    bad.write_text("candidates: {source: plane, count: -1}\n")
    with pytest.raises(ConfigError, match=r"bad.yaml: candidates.count: Input should be greater"):
        load_config(bad, ["seed=1"])
    flat = ROOT / "configs" / "flat_surface.yaml"
    with pytest.raises(ConfigError, match=r"^--set robot.pose.xyz: unknown key 'robot.pose'"):
        load_config(flat, ["robot.pose.xyz=[0, 0, 0]"])
    with pytest.raises(ConfigError, match=r"^--set environment.table.size: expected 3 values"):
        load_config(flat, ["environment.table.size=[1, 2]"])
