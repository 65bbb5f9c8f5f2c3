"""The error contract: one-line messages, and the evidence as attributes."""

from __future__ import annotations

import pickle
from pathlib import Path

import numpy as np
import pytest

import gcm_pipeline
from gcm_pipeline.errors import (
    ConfigError,
    GcmError,
    GeometryError,
    InputError,
    RobotSpecError,
    choice_error,
    unknown_choice,
)
from gcm_pipeline.geometry.bowyer_watson import delaunay
from gcm_pipeline.robot.manipulability import manipulability


def test_an_error_without_evidence_keeps_its_message_and_has_none() -> None:
    err = InputError("grasps.csv: empty file")
    assert str(err) == "grasps.csv: empty file"
    assert err.args == ("grasps.csv: empty file",)
    assert (err.key, err.value, err.choices, err.path, err.row) == (None,) * 5


def test_evidence_is_keyword_only_and_the_message_is_unchanged() -> None:
    err = InputError("f.csv:3: column 'x': not a number: 'a'", path=Path("f.csv"), row=3, key="x")
    assert str(err) == "f.csv:3: column 'x': not a number: 'a'"
    assert (err.path, err.row, err.key) == (Path("f.csv"), 3, "x")
    with pytest.raises(TypeError):
        GcmError("m", lines=3)  # type: ignore[call-arg]


def test_evidence_survives_pickling_as_a_worker_process_returns_it() -> None:
    err = ConfigError("bad", key="ik.backend", value="pinochio", choices=["a", "b"])
    back = pickle.loads(pickle.dumps(err))
    assert type(back) is ConfigError and str(back) == "bad"
    assert (back.key, back.value, back.choices) == ("ik.backend", "pinochio", ("a", "b"))


def test_choice_error_has_unknown_choices_message_and_the_evidence() -> None:
    err = choice_error(ConfigError, "IK backend", "pinochio", ("trac_ik", "pinocchio"), key="ik")
    assert isinstance(err, ConfigError)
    assert str(err) == unknown_choice("IK backend", "pinochio", ("trac_ik", "pinocchio"))
    assert "did you mean 'pinocchio'?" in str(err)
    assert (err.key, err.value, err.choices) == ("ik", "pinochio", ("pinocchio", "trac_ik"))
    pre = choice_error(InputError, "joint", "j9", ["j1"], prefix="robot 'r': home: ")
    assert str(pre).startswith("robot 'r': home: unknown joint 'j9'")
    assert pre.key is None and pre.choices == ("j1",)


def test_user_errors_are_gcm_errors():
    """The root of the bad-input errors: the CLI turns exactly these into exit 2."""
    assert issubclass(InputError, GcmError) and issubclass(RobotSpecError, GcmError)


def test_errors_share_one_root() -> None:
    for name in (
        "ConfigError",
        "InputError",
        "GeometryError",
        "RobotSpecError",
        "FrameNotFoundError",
        "OutputError",
        "PublishError",
    ):
        assert issubclass(getattr(gcm_pipeline, name), gcm_pipeline.GcmError)


def test_unknown_choice_suggests_and_lists() -> None:
    msg = unknown_choice("projection", "cylindrcal", ["xy", "pca", "cylindrical", "spherical"])
    assert "did you mean 'cylindrical'" in msg
    assert "valid: cylindrical, pca, spherical, xy" in msg
    assert "\n" not in msg


def test_library_refusals_of_an_unknown_name_carry_the_evidence() -> None:
    # the package's own checks build these errors with choice_error: the same one-line
    # message as unknown_choice, plus the value and the sorted choices to act on
    with pytest.raises(GeometryError) as tri:
        delaunay(np.eye(3)[:, :2], method="qhul")
    assert str(tri.value) == (
        "unknown triangulator 'qhul' (did you mean 'qhull'?); valid: bowyer_watson, qhull"
    )
    assert (tri.value.value, tri.value.choices) == ("qhul", ("bowyer_watson", "qhull"))
    with pytest.raises(InputError) as metric:
        manipulability(None, np.zeros((1, 7)), metric="yoshikawaa")
    assert str(metric.value).startswith("unknown manipulability metric 'yoshikawaa'")
    assert metric.value.value == "yoshikawaa"
    assert metric.value.choices == tuple(sorted(metric.value.choices))
    assert "yoshikawa" in metric.value.choices
