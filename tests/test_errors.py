"""User errors (``gcm_pipeline.errors``): one root, ``GcmError``, and messages that list choices."""

from __future__ import annotations

import gcm_pipeline
from gcm_pipeline.errors import GcmError, InputError, RobotSpecError, unknown_choice


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
