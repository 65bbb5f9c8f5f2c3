"""The user errors share one root, ``GcmError``: the CLI turns exactly these into exit 2."""

from __future__ import annotations

from gcm_pipeline.errors import GcmError, InputError, RobotSpecError


def test_user_errors_are_gcm_errors():
    """The root of every error above: the CLI turns exactly these into exit 2."""
    assert issubclass(InputError, GcmError) and issubclass(RobotSpecError, GcmError)
