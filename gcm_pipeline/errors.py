"""Project exceptions.

Every error a user can cause (a bad config key, an unreadable file, a
non-rigid matrix, an unknown robot) is a :class:`GcmError`. The CLI prints
such an error as one line ``error: <message>`` and exits with status 2;
any other exception is a bug and keeps its traceback.

Messages name the key, file, row or value at fault and, where there is a
closed set of valid values, list them (see :func:`unknown_choice`).
"""

from __future__ import annotations

import difflib
from collections.abc import Iterable

__all__ = [
    "ConfigError",
    "FrameNotFoundError",
    "GcmError",
    "GeometryError",
    "InputError",
    "OutputError",
    "PublishError",
    "RobotSpecError",
    "unknown_choice",
]


class GcmError(Exception):
    """Root of every error a user of gcm_pipeline can cause."""


class ConfigError(GcmError):
    """A config file or value is invalid (names the key at fault)."""


class InputError(GcmError):
    """Input data (grasp poses, files, arrays) is invalid."""


class GeometryError(InputError):
    """Geometric input violates a precondition (non-rigid, non-finite, degenerate)."""


class RobotSpecError(GcmError):
    """A robot spec cannot be found or is invalid."""


class FrameNotFoundError(RobotSpecError):
    """A frame named in a robot spec does not exist in the model."""


class OutputError(GcmError):
    """The run directory cannot be written (exists, is a file, not writable)."""


class PublishError(GcmError):
    """Publishing results failed (meshcat server unreachable, browser missing)."""


def unknown_choice(kind: str, value: object, choices: Iterable[str]) -> str:
    """Build the message for a value outside a closed set of names.

    Args:
        kind: What the value names, e.g. ``"projection"``.
        value: The value given by the user.
        choices: The valid names.

    Returns:
        A one-line message naming the value, the closest valid name if any
        is close, and all valid names.
    """
    names = sorted(str(c) for c in choices)
    close = difflib.get_close_matches(str(value), names, n=1, cutoff=0.6)
    hint = f" (did you mean {close[0]!r}?)" if close else ""
    return f"unknown {kind} {value!r}{hint}; valid: {', '.join(names)}"
