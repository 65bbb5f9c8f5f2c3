"""One formatter of invalid values for every YAML front-end: run configs, studies, robot specs."""

from __future__ import annotations

import numpy as np
import pytest
import yaml

from gcm_pipeline.config import load_config, read_study
from gcm_pipeline.config.robot_spec import load_spec
from gcm_pipeline.errors import ConfigError, InputError, RobotSpecError
from gcm_pipeline.robot.ik import solve_ik

BASE = {
    "object": {"shape": "plane", "dims": {"size": [0.4, 0.4]}},
    "candidates": {"source": "plane"},
}


def _write(path, data):
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    return path


def _one_line(exc: pytest.ExceptionInfo) -> str:
    text = str(exc.value)
    assert "\n" not in text
    return text


def test_an_unknown_key_reads_the_same_in_a_config_a_study_and_a_robot_spec(tmp_path):
    cfg = _write(tmp_path / "run.yaml", {**BASE, "ik": {"backnd": "mink"}})
    with pytest.raises(ConfigError) as run:
        load_config(cfg)
    assert _one_line(run) == (
        f"{cfg}: unknown key 'ik.backnd' (did you mean 'ik.backend'?); valid keys here: "
        "backend, orientation_tolerance, position_tolerance, select, solutions, workers"
    )
    assert (run.value.key, run.value.value) == ("ik.backnd", "backnd")
    assert run.value.choices == (
        "backend",
        "orientation_tolerance",
        "position_tolerance",
        "select",
        "solutions",
        "workers",
    )

    study = _write(
        tmp_path / "study.yaml", {"base": BASE, "sweep": {"object_pose": {"x": [0.1], "yy": [0]}}}
    )
    with pytest.raises(ConfigError) as sweep:
        read_study(study)
    assert _one_line(sweep) == (
        f"{study}: unknown pose key 'sweep.object_pose.yy' (did you mean "
        "'sweep.object_pose.y'?); valid keys here: region, x, y, yaw_deg, z"
    )
    assert (sweep.value.key, sweep.value.value) == ("sweep.object_pose.yy", "yy")
    assert sweep.value.choices == ("region", "x", "y", "yaw_deg", "z")

    spec = {"name": "arm", "model": {"example_robot_data": "panda", "urfd": "x.urdf"}}
    spec_file = _write(tmp_path / "arm.yaml", {**spec, "grasp_frame": "panda_hand_tcp"})
    with pytest.raises(RobotSpecError) as robot:
        load_spec(spec_file)
    assert _one_line(robot) == (
        f"robot spec {str(spec_file)!r}: unknown key 'model.urfd' (did you mean "
        "'model.urdf'?); valid keys here: example_robot_data, package_dirs, "
        "robot_descriptions, srdf, urdf"
    )


def test_a_wrong_value_names_the_key_the_value_and_the_choices(tmp_path):
    cfg = _write(tmp_path / "run.yaml", {**BASE, "manifold": {"projection": "cylindrcal"}})
    with pytest.raises(ConfigError) as run:
        load_config(cfg)
    assert _one_line(run) == (
        f"{cfg}: manifold.projection: unknown value 'cylindrcal' (did you mean "
        "'cylindrical'?); valid: cylindrical, pca, spherical, xy"
    )
    assert (run.value.key, run.value.value) == ("manifold.projection", "cylindrcal")
    assert run.value.choices == ("cylindrical", "pca", "spherical", "xy")
    study = _write(
        tmp_path / "study.yaml",
        {"base": BASE, "sweep": {"object_pose": {"x": [0.1], "region": "tabel"}}},
    )
    with pytest.raises(ConfigError) as sweep:
        read_study(study)
    assert _one_line(sweep) == (
        f"{study}: sweep.object_pose.region: expected 'table' or {{min: [x, y], "
        "max: [x, y]}, got 'tabel'"
    )
    assert (sweep.value.key, sweep.value.value) == ("sweep.object_pose.region", "tabel")


def test_the_robot_package_takes_a_robot_not_a_name():
    """A spec name is read by the config layer (gcm_pipeline.load_robot), not inside robot/."""
    with pytest.raises(
        InputError, match=r"robot must be a Robot or a RobotSpec.*load_robot.*'panda'"
    ):
        solve_ik("panda", np.eye(4)[None])


def test_a_misspelt_required_key_is_named_with_the_key_meant(tmp_path):
    # `candidate:` for `candidates:` is unknown and leaves `candidates` missing: the
    # message names the typo and suggests the key, not only "missing 'candidates'"
    data = {"object": BASE["object"], "candidate": BASE["candidates"]}
    with pytest.raises(ConfigError) as exc:
        load_config(_write(tmp_path / "run.yaml", data))
    assert "unknown key 'candidate' (did you mean 'candidates'?)" in _one_line(exc)


def test_a_set_override_error_carries_the_key_and_the_value(tmp_path):
    cfg = _write(tmp_path / "run.yaml", BASE)
    with pytest.raises(ConfigError) as exc:
        load_config(cfg, ["ik.solutions=-3"])
    assert _one_line(exc).startswith("--set ik.solutions")
    assert (exc.value.key, exc.value.value, exc.value.choices) == ("ik.solutions", -3, None)


def test_a_missing_key_names_the_key_and_no_value(tmp_path):
    with pytest.raises(ConfigError) as exc:
        load_config(_write(tmp_path / "run.yaml", {"object": BASE["object"]}))
    assert "missing required key 'candidates'" in _one_line(exc)
    assert (exc.value.key, exc.value.value, exc.value.choices) == ("candidates", None, None)


@pytest.mark.parametrize(
    ("assignment", "key", "message"),
    [
        ("ik.backend", None, "expected KEY=VALUE"),
        ("ik..backend=mink", "ik..backend", "empty key part"),
        ("ik.backend.x=1", "ik.backend.x", "'backend' is not a section"),
    ],
)
def test_a_malformed_set_names_the_assignment(tmp_path, assignment, key, message):
    cfg = _write(tmp_path / "run.yaml", {**BASE, "ik": {"backend": "pinocchio"}})
    with pytest.raises(ConfigError, match=message) as exc:
        load_config(cfg, [assignment])
    assert _one_line(exc).startswith(f"--set '{assignment}'")
    assert (exc.value.key, exc.value.value) == (key, assignment)
