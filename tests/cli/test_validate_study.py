"""gcm validate on a study file: checked as gcm study checks it, what it would run printed."""

from __future__ import annotations

import pytest
import yaml
from helpers import BOTTLE, CONFIGS, FLAT, assert_one_line_error

from gcm_pipeline.config.study import file_kind
from gcm_pipeline.errors import ConfigError
from gcm_pipeline.study import load_study

SMALL = ["candidates.count=18", "densify.subdivisions=2", "publish.html=false"]


def _write(tmp_path, data, name="study.yaml"):
    path = tmp_path / name
    path.write_text(data if isinstance(data, str) else yaml.safe_dump(data, sort_keys=False))
    return path


def test_the_example_study_validates_and_says_what_it_would_run(cli):
    path = CONFIGS / "studies" / "bottle_placement.yaml"
    code, text, err = cli("validate", path)
    assert code == 0, err
    lines = text.splitlines()
    assert lines[:7] == [
        f"# {path}: ok (a study file)",
        f"#   base        {BOTTLE} (a valid run config)",
        "#   object_pose x 7 values 0.2 .. 0.8; y 7 values -0.45 .. 0.45; yaw_deg [0, 20]; "
        "region table",
        "#   objects     cylinder",
        "#   placements  98 + up to 49 from refinement (1 round(s), shrink 0.5); "
        "max_placements 200",
        "#   robot       panda, ik pinocchio, ranking combined",
        f"#   run it      gcm study {path} --out DIR",
    ]
    # the YAML after the comments is the study itself, and loads as one
    data = yaml.safe_load(text)
    assert data["base"] == str(BOTTLE)
    assert load_study(data).count() == 98


def test_a_region_a_base_pose_and_objects_are_counted_as_gcm_study_counts(cli, tmp_path):
    data = {
        "base": str(BOTTLE),
        "set": SMALL,
        "sweep": {
            "object_pose": {
                "x": {"from": 0.3, "to": 0.7, "steps": 5},
                "region": {"min": [0.35, -1], "max": [0.65, 1]},
            },
            "base_pose": {"yaw_deg": [0, 30]},
            "objects": [{"name": "a"}, {"name": "b", "set": ["candidates.count=9"]}],
        },
        "max_placements": 10,
    }
    path = _write(tmp_path, data)
    code, text, err = cli("validate", path)
    assert code == 0, err
    grid = load_study(path).count()
    assert grid == 3 * 2 * 2
    assert "#   object_pose x 5 values 0.3 .. 0.7; region box [0.35, -1.0] .. [0.65, 1.0]" in text
    assert "#   base_pose   yaw_deg [0, 30]" in text
    assert "#   objects     a, b" in text
    assert (
        "#   placements  12 (of 20 combinations; the others lie outside the region); "
        "more than max_placements 10: gcm study needs --force"
    ) in text


@pytest.mark.parametrize(
    ("data", "fragments"),
    [
        (
            {"base": str(BOTTLE), "sweep": {"object_pose": {"x": [0.4], "yw_deg": [0]}}},
            ["unknown pose key 'sweep.object_pose.yw_deg'", "did you mean"],
        ),
        (
            {"base": str(BOTTLE), "sweeep": {"object_pose": {"x": [0.4]}}},
            ["unknown key 'sweeep'", "did you mean 'sweep'"],
        ),
        (
            {"base": str(BOTTLE), "set": ["ik.backnd=mink"], "sweep": {"object_pose": {"x": [0]}}},
            ["base config", "ik.backnd"],
        ),
        (
            {"base": "missing.yaml", "sweep": {"object_pose": {"x": [0.4]}}},
            ["base: config file not found", "missing.yaml"],
        ),
        (
            {
                "base": str(BOTTLE),
                "sweep": {"object_pose": {"x": {"from": 1, "to": 0, "steps": 3}}},
            },
            ["sweep.object_pose.x", "inverted range"],
        ),
    ],
    ids=["pose-key", "top-key", "base-key", "base-file", "range"],
)
def test_a_bad_study_file_is_one_line_naming_the_key(cli, tmp_path, data, fragments):
    path = _write(tmp_path, data)
    code, _, err = cli("validate", path)
    assert_one_line_error(code, err, str(path), *fragments)


@pytest.mark.parametrize(
    ("text", "got"),
    [("foo: 1\nbar: 2\n", "its keys: bar, foo"), ("", "it is empty"), ("- 1\n", "it holds [1]")],
    ids=["unknown-keys", "empty", "list"],
)
def test_a_file_that_is_neither_says_which_kinds_were_tried(cli, tmp_path, text, got):
    path = _write(tmp_path, text, "x.yaml")
    code, _, err = cli("validate", path)
    assert_one_line_error(
        code, err, f"{path}: neither a run config nor a study file (tried both", got
    )


def test_a_misspelt_key_is_reported_by_the_kind_it_is_close_to():
    assert file_kind({"candidats": {}}, "x") == "run"
    assert file_kind({"bse": "a.yaml", "swep": {}}, "x") == "study"
    assert file_kind({"robot": {}, "sweep": {}}, "x") == "study"  # base/sweep decide
    with pytest.raises(ConfigError, match="neither"):
        file_kind({"zzz": 1}, "x")


def test_a_run_config_still_validates_as_one(cli):
    code, text, err = cli("validate", FLAT)
    assert code == 0, err
    assert text.startswith(f"# {FLAT}: ok\n") and "#   candidates  plane" in text


@pytest.mark.parametrize("flag", [["--set", "ik.backend=mink"], ["--target", "a"]])
def test_set_and_target_on_a_study_file_are_one_line(cli, tmp_path, flag):
    path = _write(tmp_path, {"base": str(BOTTLE), "sweep": {"object_pose": {"x": [0.4]}}})
    code, _, err = cli("validate", path, *flag)
    assert_one_line_error(code, err, f"{flag[0]}: {path} is a study file", "'set' key")


def test_a_missing_input_file_of_an_object_fails_validation(cli, tmp_path):
    data = {
        "base": str(BOTTLE),
        "sweep": {
            "object_pose": {"x": [0.4]},
            "objects": [
                {"name": "bottle"},
                {
                    "name": "gone",
                    "candidates": {"source": "file", "path": "gone.npy", "frame": "object"},
                },
            ],
        },
    }
    path = _write(tmp_path, data)
    code, _, err = cli("validate", path)
    assert_one_line_error(code, err, "gone.npy")
